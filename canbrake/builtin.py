"""Scenarios shipped with canbrake (package data), found by name.

``canbrake/scenarios`` is the repository's ``scenarios/`` folder (a symbolic link in the source
tree; ``pip install .`` copies the files into the package), so a user who installed canbrake
without this repository still has the papers' scenarios and their data files.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import yaml

from canbrake.scenario import ScenarioError, load_yaml

#: file suffixes of scenario files
SUFFIXES = (".yaml", ".yml")


def builtin_dir() -> Path:
    """The folder of the built-in scenarios (inside the installed package)."""
    return Path(str(resources.files("canbrake") / "scenarios"))


@dataclass(frozen=True)
class BuiltinScenario:
    """One built-in scenario: its name (file stem), file and one-line description."""

    name: str
    path: Path
    description: str


def builtin_scenarios() -> list[BuiltinScenario]:
    """Every built-in scenario, sorted by name."""
    d = builtin_dir()
    out = []
    for p in sorted(d.iterdir()) if d.is_dir() else []:
        if p.suffix in SUFFIXES and p.is_file():
            out.append(BuiltinScenario(p.stem, p, _description(p)))
    return out


def _description(p: Path) -> str:
    try:
        data = load_yaml(p.read_text())
    except (OSError, yaml.YAMLError):
        return ""
    desc = data.get("description") if isinstance(data, dict) else None
    return " ".join(str(desc).split()) if desc else ""


def find_scenario(name_or_path: str | Path) -> Path:
    """A scenario file: ``name_or_path`` itself if it exists, else the built-in scenario of that
    name (with or without ``.yaml``). Raises :class:`ScenarioError` naming the built-ins."""
    p = Path(name_or_path)
    if p.exists():
        return p
    stem = p.name[: -len(p.suffix)] if p.suffix in SUFFIXES else p.name
    if p.parent in (Path("."), Path("scenarios")):
        for b in builtin_scenarios():
            if b.name == stem:
                return b.path
    names = ", ".join(b.name for b in builtin_scenarios()) or "none"
    raise ScenarioError(f"{p}: no such scenario file, nor a built-in scenario (built-in: {names}; "
                        f"`canbrake scenarios` lists them)")


def data_files(path: Path) -> list[Path]:
    """Files under ``data/`` beside a scenario that the scenario names (relative paths in its text)."""
    d = path.parent / "data"
    if not d.is_dir():
        return []
    text = path.read_text()
    return sorted(f for f in d.rglob("*") if f.is_file() and f.name in text)


def init_scenario(name: str, dest_dir: str | Path = ".") -> list[Path]:
    """Copy the built-in scenario ``name`` (and the data files it names, under ``data/``) into
    ``dest_dir``; refuses to overwrite. Returns the files written."""
    src = find_builtin(name)
    dest = Path(dest_dir)
    todo = [(src, dest / src.name)] + [(f, dest / f.relative_to(src.parent)) for f in data_files(src)]
    clash = [str(t) for _, t in todo if t.exists()]
    if clash:
        raise ScenarioError(f"{clash[0]}: already exists; not overwritten (choose another DIR)")
    written = []
    for s, t in todo:
        t.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(s, t)
        written.append(t)
    return written


def find_builtin(name: str) -> Path:
    """The built-in scenario ``name`` (file stem, ``.yaml`` optional)."""
    stem = name[:-5] if name.endswith(".yaml") else name
    for b in builtin_scenarios():
        if b.name == stem:
            return b.path
    names = ", ".join(b.name for b in builtin_scenarios()) or "none"
    raise ScenarioError(f"{name}: not a built-in scenario (built-in: {names})")
