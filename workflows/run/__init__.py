"""One run: its plan, output directory, step table and loop, fingerprints, progress and log."""
