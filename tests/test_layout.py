"""The package's layout rules: no import cycle in warpsense/, and only the camera touches its stages."""

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "warpsense"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in PACKAGE.rglob("*.py")}


def _imports(path: Path, modules: dict) -> set[str]:
    """The warpsense modules ``path`` imports, at module level or inside functions (a `from package import name`
    that names a submodule counts as importing it)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name in modules)
        elif isinstance(node, ast.ImportFrom) and node.module and node.module in modules:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in modules)
    return found


def test_no_import_cycle_in_the_package():
    modules = _modules()
    graph = {name: _imports(path, modules) - {name} for name, path in modules.items()}
    # a package's __init__ re-exporting its own submodules is not a cycle through them
    for name in graph:
        graph[name] = {target for target in graph[name] if not target.startswith(name + ".")}
    state, stack, cycles = {}, [], []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for target in sorted(graph[node]):
            if state.get(target) == "open":
                cycles.append(stack[stack.index(target):] + [target])
            elif target not in state:
                visit(target)
        stack.pop()
        state[node] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(cycle) for cycle in cycles)


def test_config_imports_no_implementation():
    modules = _modules()
    assert _imports(modules["warpsense.config"], modules) <= {"warpsense.choices", "warpsense.files",
                                                              "warpsense.resources"}


def test_only_the_camera_touches_its_stages():
    stage_attribute = re.compile(r"(?<!warpsense\.)\bcamera\.(optics|exposure|cfa|noise|quantizer)\b")
    offenders = [f"{path.relative_to(PACKAGE.parent)}:{number}" for path in PACKAGE.rglob("*.py")
                 if "camera" not in path.relative_to(PACKAGE).parts[:1]
                 for number, line in enumerate(path.read_text().splitlines(), start=1) if stage_attribute.search(line)]
    assert not offenders, f"stage attributes read outside warpsense/camera/: {offenders}"


def test_commands_and_tools_load_models_through_the_composition_root():
    root = PACKAGE.parent
    for path in [*(PACKAGE / "commands").glob("*.py"), *(root / "tools").glob("*.py")]:
        text = path.read_text()
        assert "warpsense.train.checkpoint" not in text and "warpsense.models.sensing" not in text, path
        assert not re.search(r"from warpsense\.train\.\w+ import .*(load_system|resolve_device|colorize)", text), path


def test_the_code_cites_only_references_that_ship():
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    assert (root / "docs" / "references.md").is_file()
    unshipped = re.compile(r"SPEC|\(issue \d+|paper eq\.")
    offenders = [f"{path.relative_to(root)}:{number}" for folder in ("warpsense", "kernels")
                 for path in sorted((root / folder).rglob("*.py"))
                 for number, line in enumerate(path.read_text().splitlines(), 1) if unshipped.search(line)]
    assert offenders == []


def test_no_measurement_rounds_in_the_product():
    """The product is not a lab notebook: the README, the package, the kernels and the configs name no measurement
    round (the history of how each choice was reached is docs/records/history.md)."""
    root = PACKAGE.parent
    paths = [root / "README.md", *(path for folder in ("warpsense", "kernels", "configs")
                                   for path in sorted((root / folder).rglob("*")) if path.suffix in (".py", ".toml"))]
    rounds = re.compile(r"\bround[ -]?\d+", re.IGNORECASE)
    offenders = [f"{path.relative_to(root)}:{number}" for path in paths
                 for number, line in enumerate(path.read_text().splitlines(), 1) if rounds.search(line)]
    assert offenders == []
