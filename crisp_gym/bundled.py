"""Where the data that ships with the package is: the humanoid model, the bundled clips and their
registry, the shipped policies.

They are package data (the ``assets/`` folder installs as ``crisp_gym.assets``), found through
``importlib.resources`` so that a regular ``pip install .`` finds them as an editable install does.
MuJoCo and the clip readers need real files, so the package is used from a directory, never a zip.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

ASSETS_DIR = Path(str(files("crisp_gym.assets")))
BUNDLED_REGISTRY = ASSETS_DIR / "registry.yaml"
BUNDLED_CLIPS = ASSETS_DIR / "clips"
SHIPPED_POLICIES = ASSETS_DIR / "policies"
HUMANOID_XML = ASSETS_DIR / "humanoid" / "crisp_humanoid.xml"


def display_path(path: str | Path) -> str:
    """``path`` as ``assets/...`` when it is bundled data (reports stay machine-independent), else as given."""
    try:
        return str(Path("assets") / Path(path).resolve().relative_to(ASSETS_DIR.resolve()))
    except ValueError:
        return str(path)
