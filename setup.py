"""Packaging that pyproject.toml cannot express: the top-level configs/ folder ships in the
wheel as the package ``workflows.configs``, so ``silva demo`` and ``silva init`` work from a
plain ``pip install`` (configs/ stays the one copy in the repository); the installed models
ship as package data of ``workflows.models``."""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["pipeline*", "workflows*"]), "workflows.configs"],
    package_dir={"workflows.configs": "configs"},
    package_data={"workflows.configs": ["*.yaml"],
                  # the models installed with Silva: model.json and forests per model
                  "workflows.models": ["*/model.json", "*/card.json", "*/*.skops"]},
)
