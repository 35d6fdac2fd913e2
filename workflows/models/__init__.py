"""The models installed with Silva: one directory each beside this file, as 'silva train'
writes them (model.json and one forest per stage), with its model card in ``card.json``
(kind, training data and licences, density range, scores; nothing that changes a
prediction). ``--model NAME`` takes one wherever a model directory is accepted."""

import json
import math
from pathlib import Path

from pipeline.errors import ModelError
from pipeline.model import recorded, trained_densities

HERE = Path(__file__).resolve().parent


def installed_models() -> dict[str, Path]:
    """Name -> directory of every model installed with Silva, by name."""
    return {p.name: p for p in sorted(HERE.iterdir()) if (p / "model.json").is_file()}


def model_path(name_or_dir) -> Path:
    """The model directory ``name_or_dir`` names: an installed model's name, or a directory
    holding a model.json. A bare name that is both (say an earlier run's ``--out``) is
    refused: which was meant cannot be told. ModelError (one line) for neither or both."""
    given = str(name_or_dir)
    path = Path(name_or_dir).expanduser()
    holds_model = (path / "model.json").is_file()
    installed = installed_models()
    if given in installed:
        if holds_model:
            raise ModelError(
                f"--model {given}: both a model installed with Silva and the model directory "
                f"{path.absolute()}; write --model ./{given} for the directory, or move it")
        return installed[given]
    if holds_model:
        return path
    known = ", ".join(installed) or "none"
    what = "a directory without a model.json" if path.is_dir() else "no such model directory"
    raise ModelError(f"--model {given}: {what}, nor a model installed with Silva "
                     f"(installed: {known}; 'silva models' lists them)")


def model_summary(name: str, directory: Path) -> dict:
    """What 'silva models --json' says of one installed model: its name, kind, classes (with
    their output codes), whether it uses echo features (``echoes``), and its card (training
    data, licences, density range, scores)."""
    description = json.loads((directory / "model.json").read_text())
    card_path = directory / "card.json"
    card = json.loads(card_path.read_text()) if card_path.is_file() else {}
    return {
        "name": name,
        "kind": card.get("kind", "unknown"),
        "classes": {c["name"]: c["code"] for c in description.get("classes", ())},
        "feature_set": description.get("features.set"),
        # whether it needs each point's return numbers (a model.json without the key: no)
        "echoes": bool(recorded(description, "features.echoes")),
        "stages": len(description.get("stages", ())),
        "densities": trained_densities(description),
        "size_bytes": sum(p.stat().st_size for p in directory.iterdir() if p.is_file()),
        "path": str(directory),
        **{k: v for k, v in card.items() if k != "kind"},
    }


def models_for_density(density: float, points: int, classes: dict, besides=None
                       ) -> list[str]:
    """The installed models with these ``classes`` (name -> code) whose r1 disc on flat
    ground holds at least ``points`` points at ``density`` points per m², by name; not the
    one in the directory ``besides``."""
    fitting = []
    for name, directory in installed_models().items():
        if besides is not None and directory == Path(besides).resolve():
            continue
        description = json.loads((directory / "model.json").read_text())
        same = {c["name"]: c["code"] for c in description.get("classes", ())} == classes
        if same and density * math.pi * description["features.r1"] ** 2 >= points:
            fitting.append(name)
    return fitting
