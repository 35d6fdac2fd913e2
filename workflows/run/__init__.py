"""One run: its plan, output directory, loop over the table of steps it is given (what such a
table is; the steps' floor declares the steps), fingerprints, progress and log."""
