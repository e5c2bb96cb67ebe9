"""Property-based fuzzing of every loader users feed files to: motion npz, BVH, SMPL/AMASS, RGB-D
folders, MegaSAM npz, real-robot logs, clip folders, policies and the registry.

Each loader gets valid seed files the project makes, damaged by hypothesis (bytes truncated,
flipped, overwritten, inserted or deleted; numbers in text files replaced by extreme ones; arrays
in npz files replaced by ones of other values, shapes or types). Every damaged file must either
load or raise one of the errors the CLI reports as a one-line message (``crisp_gym.cli.USER_ERRORS``),
never another exception, never a hang (each example has a deadline) and never an allocation over
2 GB (traced). The default run tries 40 files per loader; ``-m slow`` 400.
"""

from __future__ import annotations

import json
import shutil
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crisp_gym.cli import USER_ERRORS
from crisp_gym.clip import load_clip_dir, write_clip
from crisp_gym.export.motion_formats import write_motion_csv, write_motion_npz
from crisp_gym.humanoid import build_humanoid
from crisp_gym.import_motion import read_motion
from crisp_gym.reconstruct.io import read_frames
from crisp_gym.registry import list_clips, load_clip
from crisp_gym.scene import Box, floor_box
from crisp_gym.sim2real.cli import load_any
from crisp_gym.sim2real.log import RealLog, save_log
from crisp_gym.sim2real.models import SERVO_ACTUATOR, SERVO_JOINT, build_servo_pendulum_spec
from crisp_gym.train.checkpoints import load_policy
from tests.conftest import sway_motion
from tests.test_bvh import BVH_TO_OURS, CMU_UNIT, cgspeed_joints, pose_rotations, write_bvh
from tests.test_import_motion import _protomotions_file
from tests.test_recon_io import _npz_arrays, _write_tum

MAX_BYTES = 2 * 1024**3
MODEL = build_humanoid()
EXTREME_NUMBERS = ["nan", "inf", "-inf", "1e308", "-1e308", "1e-308", "0", "-0", "-1", "1e6", "99999999999999999999",
                   "", "x", "1e", "--1", "0x10"]
EXTREME_VALUES = [np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0, -1.0, 1e6, 1e-300]


def _examples(default: int) -> settings:
    return settings(max_examples=default, deadline=20_000, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


def _loads_or_explains(load: Callable[[], object]) -> None:
    """``load()`` succeeds or raises a user error with a message; its traced peak stays under 2 GB."""
    tracemalloc.start()
    try:
        load()
    except USER_ERRORS as err:
        assert str(err).strip(), f"{type(err).__name__} without a message"
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < MAX_BYTES, f"allocated {peak / 1e9:.1f} GB"


# ----------------------------------------------------------------------------- damage


@st.composite
def damaged_bytes(draw, data: bytes) -> bytes:
    """``data`` with 1-4 byte-level edits."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        edit = draw(st.sampled_from(["truncate", "flip", "overwrite", "insert", "delete"]))
        if edit == "truncate":
            del out[at:]
        elif edit == "flip" and out:
            out[at] ^= 1 << draw(st.integers(0, 7))
        elif edit == "overwrite":
            chunk = draw(st.binary(min_size=1, max_size=16))
            out[at:at + len(chunk)] = chunk
        elif edit == "insert":
            out[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif edit == "delete":
            del out[at:at + draw(st.integers(1, 64))]
    return bytes(out)


@st.composite
def damaged_text(draw, text: str) -> str:
    """``text`` with 1-3 edits: a number replaced by an extreme or malformed one, a line dropped or
    repeated."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 3))):
        k = draw(st.integers(0, len(lines) - 1))
        edit = draw(st.sampled_from(["number", "number", "drop", "repeat"]))
        tokens = lines[k].split(" ")
        numeric = [i for i, tok in enumerate(tokens) if tok.strip().lstrip("-").replace(".", "", 1).isdigit()]
        if edit == "number" and numeric:
            tokens[draw(st.sampled_from(numeric))] = draw(st.sampled_from(EXTREME_NUMBERS))
            lines[k] = " ".join(tokens)
        elif edit == "drop" and len(lines) > 1:
            del lines[k]
        elif edit == "repeat":
            lines.insert(k, lines[k])
    return "\n".join(lines)


@st.composite
def damaged_arrays(draw, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``arrays`` with one removed, or replaced by one of extreme values, another shape or type."""
    out = dict(arrays)
    key = draw(st.sampled_from(sorted(arrays)))
    edit = draw(st.sampled_from(["values", "values", "shape", "dtype", "drop", "empty", "scalar"]))
    value = np.asarray(arrays[key])
    if edit == "values" and value.size and value.dtype.kind == "f":
        flat = value.astype(float).ravel().copy()
        flat[draw(st.integers(0, flat.size - 1))] = draw(st.sampled_from(EXTREME_VALUES))
        out[key] = flat.reshape(value.shape)
    elif edit == "shape" and value.ndim:
        axis = draw(st.integers(0, value.ndim - 1))
        out[key] = np.delete(value, slice(0, max(1, value.shape[axis] // 2)), axis=axis) \
            if draw(st.booleans()) else np.expand_dims(value, axis)
    elif edit == "dtype":
        out[key] = value.astype(draw(st.sampled_from(["U3", "int8", "bool", "complex64"])), copy=True) \
            if value.dtype.kind != "U" else np.zeros(value.shape)
    elif edit == "drop":
        del out[key]
    elif edit == "empty":
        out[key] = np.zeros((0,) + value.shape[1:], dtype=value.dtype)
    else:
        out[key] = np.asarray(draw(st.sampled_from(EXTREME_VALUES)))
    return out


# ----------------------------------------------------------------------------- seed files


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    """Valid files of every kind, made here."""
    root = tmp_path_factory.mktemp("seeds")
    motion = sway_motion(frames=20)
    files = {"motion": motion.save(root / "motion.npz")}
    for layout in ("amass", "smpl", "beyondmimic"):
        files[layout] = write_motion_npz(motion, root / f"{layout}.npz", layout=layout)
    files["csv"] = write_motion_csv(motion, root / "motion.csv")
    joints = cgspeed_joints(CMU_UNIT, BVH_TO_OURS.T)
    rotations, root_pos = pose_rotations([j[0] for j in joints], BVH_TO_OURS.T)
    frames = 12  # the first pose, drifting at walking pace
    drift = root_pos[0] + np.outer(np.arange(frames) / 30.0, [1.0, 0.0, 0.0])
    files["bvh"] = write_bvh(root / "walk.bvh", joints, np.repeat(rotations[:1], frames, axis=0),
                             drift @ BVH_TO_OURS / CMU_UNIT)
    files["clip"] = write_clip(root / "clip", [floor_box(), Box(center=[1.0, 0.8, 0.1], half_size=[0.3, 0.3, 0.1])],
                               motion, {"source": "test"})
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.8, 2.5, (3, 12, 16))
    rgb = rng.integers(0, 255, (3, 12, 16, 3), dtype=np.uint8)
    _write_tum(root / "tum", depth, rgb, poses=np.tile(np.eye(4), (3, 1, 1)))
    files["tum"] = root / "tum"
    megasam = _npz_arrays()
    np.savez(root / "megasam.npz", **megasam)
    files["megasam"] = root / "megasam.npz"
    files["model"] = root / "servo.xml"
    files["model"].write_text(build_servo_pendulum_spec().to_xml())
    t = np.arange(50) * 0.005
    log = RealLog(time=t, qpos=0.3 * np.sin(t)[:, None], ctrl=0.3 * np.sin(t + 0.1)[:, None],
                  joint_names=(SERVO_JOINT,), actuator_names=(SERVO_ACTUATOR,))
    files["log"] = save_log(log, root / "log.npz")
    entries = [{"position": float(np.sin(x)), "speed": 0.0, "load": 0.0, "input_volts": 7.4, "temp": 30.0,
                "goal_position": float(np.sin(x + 0.1)), "torque_enable": True, "timestamp": float(x)} for x in t]
    files["servo"] = root / "servo.json"
    files["servo"].write_text(json.dumps({"mass": 0.49, "length": 0.1, "kp": 400, "vin": 7.4, "motor": "xl330",
                                          "trajectory": "sin", "dt": 0.005, "entries": entries}, indent=0))
    files["policy"] = Path(__file__).resolve().parents[1] / "assets" / "policies" / "bundled" / "policy.pt"
    files["protomotions"] = _protomotions_file(root / "walk.motion", motion, MODEL)
    return files


def _write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


MOTION_FILES = ["motion", "amass", "smpl", "beyondmimic"]


@pytest.mark.parametrize("kind", [*MOTION_FILES, "megasam", "log"])
@pytest.mark.parametrize("examples", [pytest.param(40, id="40"), pytest.param(400, id="400", marks=pytest.mark.slow)])
def test_damaged_npz_files(seeds, tmp_path, kind, examples):
    seed = seeds[kind]
    with np.load(seed, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    load = {"megasam": read_frames, "log": lambda p: load_any(p, seeds["model"])}.get(
        kind, lambda p: read_motion(p, model=MODEL))

    @_examples(examples)
    @given(data=st.one_of(damaged_bytes(seed.read_bytes()), damaged_arrays(arrays)))
    def check(data):
        path = tmp_path / seed.name
        if isinstance(data, dict):
            np.savez(path, **data)
        else:
            _write(path, data)
        _loads_or_explains(lambda: load(path))

    check()


@pytest.mark.parametrize("kind", ["bvh", "csv", "servo"])
@pytest.mark.parametrize("examples", [pytest.param(40, id="40"), pytest.param(400, id="400", marks=pytest.mark.slow)])
def test_damaged_text_files(seeds, tmp_path, kind, examples):
    seed = seeds[kind]
    load = (lambda p: load_any(p, None)) if kind == "servo" else (lambda p: read_motion(p, model=MODEL))

    @_examples(examples)
    @given(data=st.one_of(damaged_text(seed.read_text()), damaged_bytes(seed.read_bytes())))
    def check(data):
        path = _write(tmp_path / seed.name, data)
        _loads_or_explains(lambda: load(path))

    check()


@pytest.mark.parametrize("kind, loader", [("clip", load_clip_dir), ("tum", lambda p: read_frames(p, progress=False))])
@pytest.mark.parametrize("examples", [pytest.param(40, id="40"), pytest.param(400, id="400", marks=pytest.mark.slow)])
def test_damaged_folders(seeds, tmp_path, kind, loader, examples):
    """One file of a clip folder or an RGB-D (TUM) folder damaged."""
    seed = seeds[kind]
    files = sorted(p.relative_to(seed) for p in seed.rglob("*") if p.is_file())

    @_examples(examples)
    @given(name=st.sampled_from(files), data=st.data())
    def check(name, data):
        folder = tmp_path / kind
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(seed, folder)
        original = (seed / name).read_bytes()
        damage = damaged_bytes(original)
        if name.suffix in (".json", ".txt", ".xml"):
            damage = st.one_of(damage, damaged_text(original.decode()))
        _write(folder / name, data.draw(damage))
        _loads_or_explains(lambda: loader(folder))

    check()


@pytest.mark.parametrize("kind", ["policy", "protomotions"])
@pytest.mark.parametrize("examples", [pytest.param(25, id="25"), pytest.param(250, id="250", marks=pytest.mark.slow)])
def test_damaged_torch_files(seeds, tmp_path, kind, examples):
    """Policies and ProtoMotions motions: torch zip archives read with ``weights_only``."""
    seed = seeds[kind]
    load = load_policy if kind == "policy" else (lambda p: read_motion(p, model=MODEL))

    @_examples(examples)
    @given(data=damaged_bytes(seed.read_bytes()))
    def check(data):
        path = _write(tmp_path / seed.name, data)
        _loads_or_explains(lambda: load(path))

    check()


@pytest.mark.parametrize("examples", [pytest.param(40, id="40"), pytest.param(400, id="400", marks=pytest.mark.slow)])
def test_damaged_registry(seeds, tmp_path, monkeypatch, examples):
    registry = tmp_path / "registry.yaml"
    monkeypatch.setenv("CRISP_GYM_USER_REGISTRY", str(registry))
    text = (f"clips:\n  walk:\n    path: {seeds['clip']}\n    tags: [test, walk]\n"
            f"  other:\n    path: {seeds['clip']}\n")

    def load_all() -> None:
        for name in list_clips():
            load_clip(name)

    @_examples(examples)
    @given(data=st.one_of(damaged_text(text), damaged_bytes(text.encode())))
    def check(data):
        _write(registry, data)
        _loads_or_explains(load_all)

    check()
