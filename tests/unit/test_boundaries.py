"""Import boundaries the architecture promises, read from the source (no imports run): only the
transport module talks to Zenoh, and the replay reaches other packages only through common/."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: modules (relative to the repository root) that may import zenoh: the network-facing ones
ZENOH_MODULES = {"common/transport.py"}


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports, at any depth (function-level imports too)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def _sources(*dirs: str) -> list[Path]:
    return [p for d in dirs for p in sorted((ROOT / d).rglob("*.py"))]


def test_only_the_transport_module_imports_zenoh():
    files = _sources("actor", "learner", "replay", "common", "zenrl")
    assert len(files) > 20 and (ROOT / "common/transport.py") in files
    offenders = sorted(str(p.relative_to(ROOT)) for p in files
                       if str(p.relative_to(ROOT)) not in ZENOH_MODULES
                       and any(m == "zenoh" or m.startswith("zenoh.") for m in _imports(p)))
    assert not offenders, f"import zenoh outside {sorted(ZENOH_MODULES)}: {offenders}"
    assert "zenoh" in _imports(ROOT / "common/transport.py")


def test_the_replay_imports_only_common():
    bad = {str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.startswith("zenrl.")
                                            and not m.startswith(("zenrl.common", "zenrl.replay")))
           for p in _sources("replay")}
    assert not {k: v for k, v in bad.items() if v}, bad


def test_the_league_imports_only_common_and_not_zenoh():
    files = _sources("league")
    assert files
    bad = {str(p.relative_to(ROOT)): sorted(m for m in _imports(p)
                                            if (m.startswith("zenrl.") and not m.startswith(("zenrl.common", "zenrl.league")))
                                            or m == "zenoh" or m.startswith("zenoh."))
           for p in files}
    assert not {k: v for k, v in bad.items() if v}, bad
