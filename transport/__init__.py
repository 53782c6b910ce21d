"""Sources and sinks: each module speaks one file or wire format.

May import ``livecap.core`` only (never solvers, the modes or the pipeline).
"""
