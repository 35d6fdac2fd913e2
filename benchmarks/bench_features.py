"""Throughput of the local moment invariants: a thin wrapper of ``silva bench features``.

    python benchmarks/bench_features.py [PATH] [options of silva bench features]

PATH defaults to the Oakland validation scene
(``../shared/data/oakland/oakland_part3_am.xyz_label_conf``); every option is that of
``silva bench features`` (``silva bench features --help``), e.g. ``--points 300000`` on
``../shared/data/tls/LPine1_demo.laz`` for terrestrial-scan density.
"""

import sys
from pathlib import Path

from workflows.cli.main import main

DEFAULT_DATA = (Path(__file__).resolve().parents[2] / "shared" / "data" / "oakland"
                / "oakland_part3_am.xyz_label_conf")

if __name__ == "__main__":
    args = sys.argv[1:]
    if not args or args[0].startswith("-"):
        args = [str(DEFAULT_DATA), *args]
    main(["bench", "features", *args])
