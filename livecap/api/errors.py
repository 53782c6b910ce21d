"""The API's typed error: a ValueError (what the commands already catch) that names the parameter."""

from __future__ import annotations


class ApiError(ValueError):
    """A bad argument to a ``livecap`` API call; ``parameter`` names it."""

    def __init__(self, parameter: str, message: str) -> None:
        super().__init__(f"{parameter}: {message}")
        self.parameter = parameter
