"""Sources and sinks: each module speaks one file or wire format. Never imports solvers."""
