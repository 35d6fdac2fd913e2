"""The points a run leaves out, resolved once from the configuration's ``data`` section
(``DataConfig.points_filter``) and applied the same way by ingest, by its density pass and
by the export.

- ``exclude_codes`` / ``exclude_withheld``: points of those classification codes, or with the
  withheld flag, are in no scene (no neighbourhood, no training sample, no metric) and the
  export writes them unchanged;
- ``keep_codes`` (``data.drop_unlisted``): labelled points whose code is in no class and not
  ignored are left out of the labelled scenes; the export finds them missing.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PointFilter:
    """The ingest filters of a run (module docstring)."""

    exclude_codes: tuple[int, ...] = ()
    exclude_withheld: bool = False
    keep_codes: tuple[int, ...] | None = None  # data.drop_unlisted: the listed codes

    @property
    def excludes(self) -> bool:
        """Whether any point may be left out: the export then marks them (``Excluded``)."""
        return bool(self.exclude_codes or self.exclude_withheld or self.keep_codes is not None)

    def fields(self, label_field: str | None) -> tuple[str, ...]:
        """The point dimensions to read: the labels (``label_field``; None for a scene
        without labels), and what the filters look at."""
        fields = [label_field] if label_field is not None else []
        if self.exclude_codes:
            fields.append("classification")
        if self.exclude_withheld:
            fields.append("withheld")
        return tuple(dict.fromkeys(fields))

    def excluded(self, fields: dict) -> np.ndarray | None:
        """bool (n,) mask of the points ``exclude_codes`` and ``exclude_withheld`` leave
        out, from a batch's fields; None when neither is set."""
        mask = None
        if self.exclude_codes:
            mask = np.isin(np.asarray(fields["classification"]), list(self.exclude_codes))
        if self.exclude_withheld:
            withheld = np.asarray(fields["withheld"]).astype(bool)
            mask = withheld if mask is None else mask | withheld
        return mask

    def unlisted(self, raw_labels: np.ndarray) -> np.ndarray | None:
        """bool (n,) mask of the labelled points ``keep_codes`` leaves out (their source
        codes ``raw_labels``); None without ``data.drop_unlisted``."""
        if self.keep_codes is None:
            return None
        return ~np.isin(raw_labels, self.keep_codes)
