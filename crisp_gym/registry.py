"""Clip registries: names to clip directories.

Two YAML files are read, the user's entries shadowing the bundled ones:

* the bundled ``assets/registry.yaml`` (clips in ``assets/clips``, package data);
* the user registry, ``$CRISP_GYM_USER_REGISTRY`` or ``<user data dir>/crisp-gym/registry.yaml``,
  where ``crisp import-motion`` and ``crisp reconstruct --register`` add clips. It never
  lives inside the installed package.

Both have the form ``clips: {NAME: {path: DIR, tags: [..]}}``; a relative ``path`` is
relative to the registry file.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import platformdirs
import yaml

from crisp_gym.atomic import write_text
from crisp_gym.bundled import BUNDLED_REGISTRY
from crisp_gym.clip import CLIP_FILES, Clip, load_clip_dir

_CLIP_NAME = re.compile(r"\w[\w.+-]*")


def user_registry_path() -> Path:
    """Where user clips are registered."""
    override = os.environ.get("CRISP_GYM_USER_REGISTRY")
    if override:
        return Path(override)
    return Path(platformdirs.user_data_dir("crisp-gym")) / "registry.yaml"


def user_clips_dir() -> Path:
    """Where ``crisp import-motion`` and ``crisp synth-clips --kind`` write clips by default."""
    return Path(platformdirs.user_data_dir("crisp-gym")) / "clips"


def _read(path: Path) -> dict[str, dict]:
    if not path.is_file():
        return {}
    try:
        content = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not a readable registry ({type(err).__name__}: "
                         f"{str(err).splitlines()[0]}); fix or remove it") from None
    clips = content.get("clips", {}) if isinstance(content, dict) else None
    if not isinstance(clips, dict):
        raise ValueError(f"{path} must have the form 'clips: {{NAME: {{path: DIR, tags: [...]}}}}'")
    entries = {}
    for name, entry in clips.items():
        if not isinstance(name, str) or not _CLIP_NAME.fullmatch(name):
            raise ValueError(f"{path}: {name!r} is not a plain clip name (a letter, digit or '_', then also "
                             f"'.', '+', '-')")
        if not isinstance(entry, dict) or not isinstance(entry.get("path"), str):
            raise ValueError(f"{path}: clip {name!r} needs a 'path' (a folder)")
        tags = entry.get("tags", [])
        if not isinstance(tags, list) or not all(isinstance(t, str) for t in tags):
            raise ValueError(f"{path}: the tags of clip {name!r} must be a list of words, got {tags!r}")
        clip_path = Path(entry["path"]).expanduser()
        if not clip_path.is_absolute():
            clip_path = path.parent / clip_path
        entries[str(name)] = {"path": clip_path, "tags": tags}
    return entries


def list_clips() -> dict[str, dict]:
    """All registered clips: name -> {"path": Path, "tags": [...]} (user entries win)."""
    return {**_read(BUNDLED_REGISTRY), **_read(user_registry_path())}


def _is_clip_dir(path: Path) -> bool:
    return path.is_dir() and any((path / f).is_file() for f in CLIP_FILES)


def _names_a_directory(source: str | os.PathLike, names: set[str]) -> bool:
    """Whether ``source`` means the directory of that spelling: one that holds clip files, or
    any directory when nothing registered is spelled so (a run folder called ``bundled`` in
    the working directory must not hide the tag)."""
    candidate = Path(source).expanduser()
    return _is_clip_dir(candidate) or (candidate.is_dir() and str(source) not in names)


def resolve_clip(name_or_path: str | os.PathLike) -> Path:
    """The directory ``name_or_path`` if it holds a clip, else the registered clip of that name
    (an unregistered directory is returned as it is, for the loader to say what it lacks)."""
    clips = list_clips()
    if _names_a_directory(name_or_path, set(clips)):
        return Path(name_or_path).expanduser()
    name = str(name_or_path)
    if name not in clips:
        raise ValueError(f"unknown clip {name!r}: not a directory and not registered; "
                         f"registered clips are {sorted(clips)}")
    path = clips[name]["path"]
    if not path.is_dir():
        registry = user_registry_path() if name in _read(user_registry_path()) else BUNDLED_REGISTRY
        raise FileNotFoundError(f"clip {name!r} of {registry} is registered at {path}, which is not a folder "
                                f"(moved or deleted? `crisp import-motion`/`crisp reconstruct --register` re-register)")
    return path


BUNDLED_TAG = "bundled"
"""The tag every clip of the bundled registry carries implicitly."""


def clips_with_tag(tag: str) -> list[str]:
    """Names of the registered clips tagged ``tag`` (sorted); :data:`BUNDLED_TAG` names the bundled clips."""
    if tag == BUNDLED_TAG:
        return sorted(_read(BUNDLED_REGISTRY))
    return sorted(name for name, entry in list_clips().items() if tag in entry["tags"])


def resolve_clip_names(source: str | os.PathLike) -> list[str | Path]:
    """What one clip source names: a clip directory or registered name (itself), else a tag's clips.

    A clip name wins over a tag of the same spelling, and both over a directory of that
    spelling that holds no clip.
    """
    clips = list_clips()
    tags = {t for entry in clips.values() for t in entry["tags"]} | {BUNDLED_TAG}
    if _names_a_directory(source, set(clips) | tags) or str(source) in clips:
        return [source]
    tagged = clips_with_tag(str(source))
    if not tagged:
        raise ValueError(f"unknown clip {str(source)!r}: not a directory, a registered clip or a tag; "
                         f"registered clips are {sorted(clips)}, tags are {sorted(tags)}")
    return tagged


def load_clip(name_or_path: str | os.PathLike) -> Clip:
    """Load a clip by registered name or directory."""
    return load_clip_dir(resolve_clip(name_or_path))


def check_clip_name(name: str) -> str:
    """``name`` if it is a plain clip name, else ValueError: letters, digits and ``_``, then also
    ``.``, ``+`` and ``-`` (no whitespace, path separator or leading dot, so a name can never
    point outside the clips folder)."""
    if not isinstance(name, str) or not _CLIP_NAME.fullmatch(name):
        raise ValueError(f"clip names must be plain names (a letter, digit or '_', then also '.', '+', '-'), "
                         f"got {name!r}")
    return name


def plain_clip_name(text: str) -> str:
    """``text`` made a plain clip name (:func:`check_clip_name`): every other character becomes
    ``_``, and a leading ``.``, ``+`` or ``-`` gets a ``_`` in front (for names taken from file stems)."""
    name = re.sub(r"[^\w.+-]", "_", text)
    return check_clip_name(name if _CLIP_NAME.fullmatch(name) else f"_{name}")


def write_registry(path: Path, clips: dict[str, tuple[str | Path, list[str]]], header: str = "") -> Path:
    """Write a registry file of ``clips`` (name -> (directory, tags)), replacing it; directories below
    the registry's folder are written relative to it, so the registry moves with its clips."""
    entries = {}
    for name, (clip_dir, tags) in clips.items():
        clip_dir = Path(clip_dir).resolve()
        if clip_dir.is_relative_to(path.resolve().parent):
            clip_dir = clip_dir.relative_to(path.resolve().parent)
        entries[check_clip_name(name)] = {"path": clip_dir.as_posix(), "tags": list(tags)}
    comment = f"# {header}\n" if header else ""
    return write_text(path, comment + yaml.safe_dump({"clips": entries}, sort_keys=True))


def register_clip(name: str, path: str | Path, tags: list[str] | None = None,
                  registry: Path | None = None) -> Path:
    """Add (or replace) a clip in the user registry; returns the registry file."""
    check_clip_name(name)
    registry = registry or user_registry_path()
    content = yaml.safe_load(registry.read_text()) if registry.is_file() else None
    content = content or {}
    content.setdefault("clips", {})[name] = {"path": str(Path(path).resolve()), "tags": list(tags or [])}
    return write_text(registry, yaml.safe_dump(content, sort_keys=True))
