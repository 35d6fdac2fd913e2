"""The ``silva`` command line: its commands, and the plan, status, sweep and bench they print."""
