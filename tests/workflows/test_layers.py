"""The layers of the code: ``pipeline/`` never imports ``workflows/``, and inside
``workflows/`` imports only go down, from the commands to the run's core (README, Layout)."""

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

#: The folders of workflows/, each above those after it: a module may import its own
#: folder's modules and those of a lower layer, never a higher one.
LAYERS = [("cli",), ("steps",), ("exec", "models"), ("run",), ("config", "store", "report")]


def _imports(path: Path) -> set[str]:
    """The modules a file imports (anywhere in it: inside functions too)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "workflows" or len(parts) < 2:
        return None
    return next((i for i, folders in enumerate(LAYERS) if parts[1] in folders), None)


def test_every_workflows_folder_has_a_layer():
    folders = {p.name for p in (REPO / "workflows").iterdir()
               if p.is_dir() and (p / "__init__.py").is_file() and p.name != "configs"}
    assert folders == {f for layer in LAYERS for f in layer}
    loose = {p.name for p in (REPO / "workflows").glob("*.py")}
    assert loose == {"__init__.py", "__main__.py"}  # every module lives in a folder


def test_imports_only_go_down():
    upward = []
    for path in sorted((REPO / "workflows").rglob("*.py")):
        own = _layer(".".join(path.relative_to(REPO).with_suffix("").parts))
        if own is None:
            continue
        upward += [f"{path.relative_to(REPO)} imports {name}" for name in _imports(path)
                   if (layer := _layer(name)) is not None and layer < own]
    assert upward == []


def test_pipeline_never_imports_workflows():
    found = [f"{path.relative_to(REPO)} imports {name}"
             for path in sorted((REPO / "pipeline").rglob("*.py"))
             for name in _imports(path) if name.split(".")[0] == "workflows"]
    assert found == []


def test_the_run_floor_names_no_step():
    """workflows/run/ is given its table of steps: it neither imports the steps' floor nor
    names its modules in a string to import them by name, which the imports above miss."""
    named = [f"{path.relative_to(REPO)}:{number}"
             for path in sorted((REPO / "workflows" / "run").rglob("*.py"))
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if "workflows.steps" in line or "resolve_name" in line
             or "import_module" in line]
    assert named == []
