"""The ready configurations shipped with Silva: the demo, the forest and urban templates and
Oakland.

They are the YAML files of the repository's ``configs/`` folder, installed as the package
``workflows.configs`` (see setup.py) and read with :mod:`importlib.resources`, so they are
there in a wheel install as in a source checkout.
"""

import contextlib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path

from pipeline.atomic import atomic_write_text
from pipeline.errors import ConfigError

#: Template name -> what it is for.
TEMPLATES = {
    "forest": "survey tiles of a forest",
    "urban": "urban scans: ground, vegetation, building, wire, pole",
    "demo": "the synthetic plots of silva demo",
    "oakland": "the Oakland urban benchmark of the paper",
}


def _resource(name: str):
    if name not in TEMPLATES:
        raise ConfigError(f"unknown template '{name}'; use one of {', '.join(TEMPLATES)}")
    return resources.files("workflows.configs").joinpath(f"{name}.yaml")


def template_text(name: str) -> str:
    """The YAML text of template ``name``."""
    return _resource(name).read_text(encoding="utf-8")


@contextlib.contextmanager
def template_path(name: str) -> Iterator[Path]:
    """A file path of template ``name`` for as long as the block runs."""
    with resources.as_file(_resource(name)) as path:
        yield path


def write_template(name: str, path: Path, *, force: bool = False) -> Path:
    """Write template ``name`` to ``path``; ConfigError when it exists and not ``force``."""
    text = template_text(name)
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path} is a directory; give the path of the config file to write, "
                          f"e.g. {path / f'{name}.yaml'}")
    if path.exists() and not force:
        raise ConfigError(f"{path} already exists; choose another path or pass --force to "
                          "overwrite it")
    atomic_write_text(path, text)
    return path
