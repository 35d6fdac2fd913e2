"""The steps of a run; each module holds its worker tasks and its coordinator function."""
