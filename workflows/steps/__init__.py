"""The steps of a run; each module holds its worker tasks and its coordinator function, and
the table of steps (:mod:`workflows.steps.table`) declares them once."""
