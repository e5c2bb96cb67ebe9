"""Policy export: a trained actor as ONNX and TorchScript, plus a JSON that says how to drive it.

The exported network is the deterministic policy (the Gaussian's mean, what evaluation runs) with
the observation normaliser folded in: it takes the raw observation tensors and returns the action.

* ``policy.onnx``: inputs ``proprio`` (B, 361), ``targets`` (B, K, 432) and, scene-aware, ``points``
  (B, N, 3), all float32 with a dynamic batch B (and N, unless the actor's point encoder is
  ``"flat"``, which fixes N); output ``action`` (B, 69).
* ``policy.pt``: TorchScript with the same signature (``torch.jit.load``).
* ``policy.json`` (:func:`policy_layout`): every input's segments (names, shapes, units, frames, how
  they are computed), the action's meaning (residual or absolute PD targets, scale, clipping, joint
  names and ranges), the PD gains and torque limits, and the control and simulation rates, so a
  robot-side runtime needs neither this package nor torch.
"""

from __future__ import annotations

import copy
import importlib.util
import json
from dataclasses import asdict
from pathlib import Path

import torch
from torch import nn

from crisp_gym.atomic import atomic_path, write_text
from crisp_gym.envs.config import TrackConfig
from crisp_gym.envs.tracking import PROPRIO_DIM, TARGET_DIM
from crisp_gym.export import POLICY_FORMATS
from crisp_gym.export.actuators import actuator_table
from crisp_gym.humanoid import BODY_NAMES, DOF_NAMES, HumanoidConfig, build_humanoid, hinge_ranges
from crisp_gym.policy.files import load_actor

ONNX_OPSET = 18

_HEADING = ("heading frame: the world frame turned about +z by the pelvis yaw, "
            "yaw = atan2(2(w z + x y), 1 - 2(y^2 + z^2)) of the pelvis quaternion (w, x, y, z); "
            "vectors are expressed in it by rotating them by -yaw")
_ROT6 = "rotation as its rotated x and z axes (matrix columns 0 and 2, 3 + 3 values)"


class DeterministicPolicy(nn.Module):
    """An actor (``TransformerActor``/``MLPActor``, or a ``FixedStdGaussian`` around one) → action means.

    The actor's observation normaliser runs inside ``forward``, so inputs are raw observations.
    """

    def __init__(self, actor: nn.Module):
        super().__init__()
        inner = getattr(actor, "actor", actor)  # FixedStdGaussian wraps the mean network
        if not hasattr(inner, "normalizer") or not hasattr(inner, "scene_aware"):
            raise ValueError(f"expected a crisp-gym actor (crisp_gym.policy.networks), got {type(actor).__name__}")
        self.actor = copy.deepcopy(inner).cpu()  # leaves the caller's module (mode, device) alone
        self.eval()
        self.scene_aware = bool(inner.scene_aware)

    @property
    def num_future_frames(self) -> int:
        return int(self.actor.normalizer.targets.shape[0])

    @property
    def fixed_num_points(self) -> int | None:
        """The number of points a flat point encoder was built for; None: any number (PointNet, scene-blind)."""
        return getattr(getattr(self.actor, "point_encoder", None), "num_points", None)

    def forward(self, proprio: torch.Tensor, targets: torch.Tensor, points: torch.Tensor | None = None) -> torch.Tensor:
        return self.actor(proprio, targets, points)

    def example_inputs(self, batch: int = 2, num_points: int = 128) -> tuple[torch.Tensor, ...]:
        """Zero observations of the right shapes (batch ≥ 2 keeps the batch dimension symbolic)."""
        inputs = (torch.zeros(batch, PROPRIO_DIM), torch.zeros(batch, self.num_future_frames, TARGET_DIM))
        return inputs + ((torch.zeros(batch, num_points, 3),) if self.scene_aware else ())


def _segments(parts: list[tuple[str, tuple[int, ...], str, str]]) -> list[dict]:
    """Flat [start, stop) offsets of consecutive segments (name, shape, units, description)."""
    out, start = [], 0
    for name, shape, units, description in parts:
        size = 1
        for s in shape:
            size *= s
        out.append({"name": name, "shape": list(shape), "start": start, "stop": start + size, "units": units,
                    "description": description})
        start += size
    return out


def policy_layout(track: TrackConfig, scene_aware: bool, num_future_frames: int,
                  humanoid: HumanoidConfig | None = None, obs_clip: float | None = 5.0) -> dict:
    """The content of ``policy.json``: inputs, output, actuation and rates (module docstring).

    ``humanoid``: the humanoid the policy drives (default :class:`~crisp_gym.humanoid.HumanoidConfig`);
    ``obs_clip``: the normaliser's bound on normalised features (``None`` when it is disabled).
    """
    n = len(BODY_NAMES)
    proprio = _segments([
        ("root_height", (1,), "m", "pelvis height above the world origin (world z)"),
        ("body_pos", (n, 3), "m", f"body positions minus the pelvis position, in the {_HEADING}"),
        ("body_rot", (n, 6), "1", f"body orientations in the heading frame, each as a {_ROT6}"),
        ("body_lin_vel", (n, 3), "m/s", "body linear velocities (of the body origins) in the heading frame"),
        ("body_ang_vel", (n, 3), "rad/s", "body angular velocities in the heading frame"),
    ])
    per_body = _segments([
        ("rot_diff", (6,), "1", f"q_sim^-1 * q_ref (reference relative to the simulated body), as a {_ROT6}"),
        ("ref_rot", (6,), "1", "reference body orientation in the heading frame, same 6 values"),
        ("pos_diff", (3,), "m", "reference minus simulated body position, in the heading frame"),
        ("ref_pos_rel_root", (3,), "m", "reference body position minus the simulated pelvis position, heading frame"),
    ])
    inputs = [
        {"name": "proprio", "shape": ["batch", PROPRIO_DIM], "dtype": "float32", "segments": proprio,
         "body_order": list(BODY_NAMES)},
        {"name": "targets", "shape": ["batch", num_future_frames, TARGET_DIM], "dtype": "float32",
         "layout": f"(K={num_future_frames}, bodies={n}, {TARGET_DIM // n}): one row per future reference frame t+1..t+K "
                   f"(at the control rate, held at the clip's last frame); per body the features below",
         "per_body_features": per_body, "body_order": list(BODY_NAMES)},
    ]
    if scene_aware:
        inputs.append({
            "name": "points", "shape": ["batch", track.num_points, 3], "dtype": "float32", "units": "m",
            "description": (f"the {track.num_points} scene surface samples nearest the pelvis, nearest first, minus "
                            f"the pelvis position, in the heading frame; samples lie on a {track.point_spacing} m "
                            f"grid on the primitives' faces within {track.point_radius} m of the motion's pelvis "
                            "path; any count works (the PointNet max-pools), the policy was trained with this one"),
        })
    ranges = hinge_ranges()
    if track.residual_actions:
        mapping = (f"PD target = reference hinge angles of frame t+1 + {track.action_scale} * clip(action, -1, 1) "
                   "(rad)")
        if track.velocity_feedforward:
            mapping += (" + clip(kd / kp * reference hinge velocities of frame t+1, "
                        f"±{track.max_feedforward_lead}) (rad; kd, kp from 'pd')")
    else:
        mapping = "PD target = (lower + upper) / 2 + (upper - lower) / 2 * clip(action, -1, 1) (rad)"
    return {
        "format_version": 1,
        "observation_normalization": {"folded_in": True, "clip": obs_clip},
        "inputs": inputs,
        "output": {"name": "action", "shape": ["batch", len(DOF_NAMES)], "dtype": "float32",
                   "mode": "residual" if track.residual_actions else "absolute", "action_scale": track.action_scale,
                   "clip": [-1.0, 1.0], "mapping": mapping, "joint_names": list(DOF_NAMES),
                   "joint_lower": ranges[:, 0].tolist(), "joint_upper": ranges[:, 1].tolist(),
                   "joint_order": "per body x, y, z hinges applied in that order (intrinsic XYZ)"},
        "control": {"control_hz": track.control_hz, "sim_hz": track.sim_hz, "substeps": track.substeps,
                    "integrator": "implicitfast"},
        "pd": actuator_table(build_humanoid(humanoid or HumanoidConfig())),
        "track_config": asdict(track),
    }


def export_inference_policy(actor: nn.Module, directory: str | Path, track: TrackConfig | None = None,
                  formats: tuple[str, ...] = POLICY_FORMATS, obs_clip: float | None = 5.0) -> list[Path]:
    """Write ``actor`` as ``policy.onnx`` / ``policy.pt`` and ``policy.json`` into ``directory``.

    ``track`` is the env configuration the policy was trained with (default: the env's defaults with
    the actor's scene awareness and number of future frames); returns the files written.
    """
    unknown = set(formats) - set(POLICY_FORMATS)
    if unknown or not formats:
        raise ValueError(f"formats must be a non-empty subset of {POLICY_FORMATS}, got {formats}")
    policy = DeterministicPolicy(actor)
    k = policy.num_future_frames
    track = track or TrackConfig(scene_aware=policy.scene_aware, num_future_frames=k)
    if track.num_future_frames != k or track.scene_aware != policy.scene_aware:
        raise ValueError(f"the actor takes {k} future frames (scene_aware={policy.scene_aware}); the track config "
                         f"says {track.num_future_frames} (scene_aware={track.scene_aware})")
    if policy.fixed_num_points not in (None, track.num_points):
        raise ValueError(f"the actor's flat point encoder takes {policy.fixed_num_points} points; the track config "
                         f"says {track.num_points}")
    directory = Path(directory)
    names = ["proprio", "targets", "points"][: 3 if policy.scene_aware else 2]
    example = policy.example_inputs(num_points=track.num_points)
    written = []
    with torch.no_grad():
        if "onnx" in formats:
            missing = [m for m in ("onnx", "onnxscript") if importlib.util.find_spec(m) is None]
            if missing:  # torch's exporter needs both and would fail deep inside with their names only
                raise ModuleNotFoundError(f"ONNX export needs {' and '.join(missing)}: pip install 'crisp-gym[export]'")
            batch = torch.export.Dim("batch")
            shapes = {"proprio": {0: batch}, "targets": {0: batch}}
            if policy.scene_aware:
                shapes["points"] = {0: batch}
                if policy.fixed_num_points is None:  # a PointNet takes any number of points
                    shapes["points"][1] = torch.export.Dim("num_points")
            with atomic_path(directory / "policy.onnx") as tmp:
                torch.onnx.export(policy, example, str(tmp), input_names=names, output_names=["action"],
                                  dynamic_shapes=shapes, dynamo=True, opset_version=ONNX_OPSET,
                                  external_data=False, verbose=False)
            written.append(directory / "policy.onnx")
        if "torchscript" in formats:
            traced = torch.jit.trace(policy, example)
            with atomic_path(directory / "policy.pt") as tmp:
                torch.jit.save(traced, str(tmp))
            written.append(directory / "policy.pt")
    layout = policy_layout(track, policy.scene_aware, k, obs_clip=obs_clip)
    layout["files"] = [p.name for p in written]
    written.append(write_text(directory / "policy.json", json.dumps(layout, indent=1) + "\n"))
    return written


def export_checkpoint(checkpoint: str | Path, directory: str | Path,
                      formats: tuple[str, ...] = POLICY_FORMATS) -> list[Path]:
    """Export the actor of a ``crisp train`` checkpoint (file or run directory) with :func:`export_inference_policy`."""
    loaded = load_actor(checkpoint)
    policy = DeterministicPolicy(loaded.actor)
    track = TrackConfig(scene_aware=loaded.scene_aware, num_future_frames=policy.num_future_frames,
                        velocity_feedforward=loaded.velocity_feedforward)
    clip = loaded.model.obs_clip if loaded.normalize_obs else None
    return export_inference_policy(loaded.actor, directory, track, formats, obs_clip=clip)
