"""Review and edit a solved take in the browser: session (math), server (aiohttp), static page."""
