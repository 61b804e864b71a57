"""What a regular (non-editable) install ships: every Python package folder of the source tree
is listed in pyproject.toml, so a wheel (the Docker image installs one) has all of zenrl."""

import tomllib

from tests.conftest import ROOT


def test_every_package_folder_is_in_the_wheel():
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(tool["packages"])
    found = set()
    for name, src in tool["package-dir"].items():
        for init in (ROOT / src).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / src)
            found.add(".".join([name, *rel.parts]) if rel.parts else name)
    # package-dir names themselves map whole folders: their subfolders must be listed too
    assert found <= listed, f"not in pyproject's packages (a wheel would lack them): {sorted(found - listed)}"
