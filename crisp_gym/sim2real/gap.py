"""Where the gap lies: the replay residual broken down by joint, time window, motion
regime, lag and frequency.

The breakdown is what points at a cause before any fitting: a gap concentrated at
velocity reversals and near-zero speed smells of friction or backlash, one growing with
speed of damping, a constant lag of delay, a gain ratio below one at high frequency of
missing inertia, a gap only in contact of the ground.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.signal import coherence, csd, welch

from crisp_gym.sim2real.replay import Replayer, Trajectory, smooth_derivative

REGIMES = ("near_zero_velocity", "reversal", "high_speed", "high_acceleration", "high_load", "contact", "swing")


def regime_masks(tr: Trajectory) -> dict[str, np.ndarray]:
    """(T, n) boolean masks of each motion regime, from the logged motion.

    Thresholds are relative to each joint's own motion (percentiles), so that they mean
    the same on a servo and on a humanoid hip.
    """
    q = tr.log.qpos
    v = tr.qvel
    a = smooth_derivative(v, tr.log.dt)
    speed = np.abs(v)
    p95 = np.percentile(speed, 95, axis=0) + 1e-9
    k = max(1, int(round(0.02 / tr.log.dt)))
    before, after = np.roll(v, k, axis=0), np.roll(v, -k, axis=0)
    moving = (np.abs(before) > 0.05 * p95) & (np.abs(after) > 0.05 * p95)
    reversal = (np.sign(before) != np.sign(after)) & moving
    reversal[:k] = reversal[-k:] = False
    load = np.abs(tr.ctrl[::tr.nsub][:, tr.act] - q) if len(tr.act) == q.shape[1] else np.abs(a)
    masks = {
        "near_zero_velocity": speed < 0.05 * p95,
        "reversal": reversal,
        "high_speed": speed > np.percentile(speed, 80, axis=0),
        "high_acceleration": np.abs(a) > np.percentile(np.abs(a), 80, axis=0),
        "high_load": load > np.percentile(load, 80, axis=0),
    }
    contact = contact_mask(tr)
    if contact is not None:
        masks["contact"] = contact
        masks["swing"] = ~contact
    return masks


def contact_mask(tr: Trajectory) -> np.ndarray | None:
    """(T, n) whether the subtree moved by each joint touches a world geom at the logged
    posture, or None when the model has no world geom to touch."""
    m = tr.model
    world = (m.geom_bodyid == 0) & ((m.geom_contype != 0) | (m.geom_conaffinity != 0))
    if not world.any():
        return None
    d = mujoco.MjData(m)
    n = len(tr.qadr)
    subtree = np.zeros((n, m.nbody), dtype=bool)
    for c, name in enumerate(tr.log.joint_names):
        root = m.jnt_bodyid[m.joint(name).id]
        for b in range(m.nbody):
            a = b
            while a > 0 and a != root:
                a = m.body_parentid[a]
            subtree[c, b] = a == root and b > 0
    out = np.zeros(tr.log.qpos.shape, dtype=bool)
    for t, q in enumerate(tr.log.qpos):
        d.qpos[tr.qadr] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        for i in range(d.ncon):
            g1, g2 = d.contact.geom1[i], d.contact.geom2[i]
            if world[g1] or world[g2]:
                body = m.geom_bodyid[g2] if world[g1] else m.geom_bodyid[g1]
                out[t] |= subtree[:, body]
    return out


def lag_seconds(reference: np.ndarray, response: np.ndarray, dt: float, max_lag: float = 0.3) -> float:
    """How much ``response`` lags ``reference`` (s, negative: leads), by the peak of the cross-correlation of
    their derivatives (derivatives remove offsets), refined by a parabola."""
    x = np.diff(reference) - np.mean(np.diff(reference))
    y = np.diff(response) - np.mean(np.diff(response))
    if np.std(x) < 1e-12 or np.std(y) < 1e-12:
        return float("nan")
    kmax = max(2, int(max_lag / dt))
    lags = np.arange(-kmax, kmax + 1)
    cc = np.array([np.dot(x[max(0, -k): len(x) - max(0, k)], y[max(0, k): len(y) - max(0, -k)]) / (len(x) - abs(k))
                   for k in lags])
    i = int(np.argmax(cc))
    shift = 0.0
    if 0 < i < len(cc) - 1:
        den = cc[i - 1] - 2 * cc[i] + cc[i + 1]
        shift = 0.5 * (cc[i - 1] - cc[i + 1]) / den if den != 0 else 0.0
    return float((lags[i] + shift) * dt)


def frequency_response(u: np.ndarray, q: np.ndarray, dt: float, bands: np.ndarray) -> list[dict]:
    """Command-to-position gain and phase at ``bands`` (Hz), with the coherence."""
    nper = min(len(u), max(64, int(4.0 / dt)))
    f, puu = welch(u, fs=1 / dt, nperseg=nper)
    _, puq = csd(u, q, fs=1 / dt, nperseg=nper)
    _, coh = coherence(u, q, fs=1 / dt, nperseg=nper)
    h = puq / np.maximum(puu, 1e-300)
    out = []
    for fb in bands:
        i = int(np.argmin(np.abs(f - fb)))
        out.append({"f_hz": float(f[i]), "gain": float(np.abs(h[i])), "phase_deg": float(np.degrees(np.angle(h[i]))),
                    "coherence": float(coh[i])})
    return out


def regime_breakdown(rep: Replayer, r: np.ndarray) -> dict[str, dict]:
    """The residual ``r`` (nwin, size-1, n) of ``rep``'s windows by motion regime
    (:func:`regime_masks`): RMS, share of samples and ratio to the overall RMS, overall and
    per joint."""
    w, mask = rep.windows, rep.mask
    names = rep.trajs[0].log.joint_names
    n = len(names)
    overall = max(float(np.sqrt(np.sum(r**2) / (mask.sum() * n))), 1e-12)
    regime_sum = {k: np.zeros(n) for k in REGIMES}
    regime_cnt = {k: np.zeros(n) for k in REGIMES}
    for ti, tr in enumerate(rep.trajs):
        sel = np.flatnonzero(w.traj == ti)
        if not len(sel):
            continue
        idx = np.minimum(w.start[sel][:, None] + np.arange(1, w.size)[None], len(tr.log.time) - 1)
        inside = mask[sel][..., None]
        for key, m in regime_masks(tr).items():
            hit = m[idx] & inside
            regime_sum[key] += np.sum(r[sel] ** 2 * hit, axis=(0, 1))
            regime_cnt[key] += hit.sum(axis=(0, 1))
    regimes = {}
    for key in REGIMES:
        if regime_cnt[key].sum() == 0:
            continue
        total = float(np.sqrt(regime_sum[key].sum() / regime_cnt[key].sum()))
        regimes[key] = {"rms": total, "share_of_samples": float(regime_cnt[key].sum() / (mask.sum() * n)),
                        "ratio_to_overall": total / overall,
                        "per_joint": {names[j]: (float(np.sqrt(regime_sum[key][j] / regime_cnt[key][j]))
                                                 if regime_cnt[key][j] else None) for j in range(n)}}
    return regimes


BANDS_HZ = (0.0, 2.0, 8.0, 20.0)
"""Lower edges of the frequency bands :func:`residual_structure` splits a residual into."""


def residual_structure(rep: Replayer, r: np.ndarray, floor: np.ndarray) -> dict:
    """What a residual ``r`` (nwin, size-1, n) still looks like, for a gap no candidate
    explains: the joints holding its excess over the noise ``floor`` (n,), how its power
    splits over frequency bands (:data:`BANDS_HZ`; windows start from the logged state, so the
    lowest band is drift within a window), and the motion regimes where it is strongest."""
    names = rep.trajs[0].log.joint_names
    mask = rep.mask
    rms = np.sqrt(np.sum(r**2, axis=(0, 1)) / mask.sum())
    excess = np.maximum(rms**2 - floor**2, 0.0)
    shares = excess / excess.sum() if excess.sum() > 0 else np.zeros(len(names))
    joints = [{"joint": names[j], "share_of_excess": float(shares[j]), "rms": float(rms[j])}
              for j in np.argsort(-shares) if shares[j] >= 0.1]
    dt = rep.trajs[0].log.dt
    power = np.abs(np.fft.rfft(r * mask[..., None], axis=1)) ** 2  # (nwin, nfreq, n)
    freq = np.fft.rfftfreq(r.shape[1], dt)
    edges = [*BANDS_HZ, np.inf]
    total = max(float(power[:, 1:].sum()), 1e-300)  # the DC bin is a window's mean offset: no band
    bands = [{"from_hz": lo, "to_hz": None if hi == np.inf else hi,
              "share_of_power": float(power[:, (freq >= max(lo, 1e-9)) & (freq < hi)].sum() / total)}
             for lo, hi in zip(edges[:-1], edges[1:])]
    regimes = regime_breakdown(rep, r)
    strongest = sorted(regimes, key=lambda k: -regimes[k]["ratio_to_overall"])
    return {"joints": joints, "bands": bands,
            "regimes": {k: regimes[k]["ratio_to_overall"] for k in strongest},
            "strongest_regime": strongest[0] if strongest else None}


def where(rep: Replayer, r: np.ndarray, open_loop: list[np.ndarray], floor: np.ndarray) -> dict:
    """The gap breakdown of the nominal replay.

    Args:
        rep: the replayer the residual ``r`` (nwin, size-1, n) came from.
        open_loop: per trajectory, the nominal model's open-loop positions (T, n), for
            lags and frequency responses (which need uninterrupted signals).
        floor: (n,) per-joint noise floor of the windowed gap.
    """
    w, mask = rep.windows, rep.mask
    names = rep.trajs[0].log.joint_names
    n = len(names)
    count = mask.sum()
    rms = np.sqrt(np.sum(r**2, axis=(0, 1)) / count)
    dt = rep.trajs[0].log.dt
    vel_pred_err = np.diff(r, axis=1) / dt * (mask[:, 1:] & mask[:, :-1])[..., None]
    rms_vel = np.sqrt(np.sum(vel_pred_err**2, axis=(0, 1)) / max(1, (mask[:, 1:] & mask[:, :-1]).sum()))
    excess = np.sqrt(np.maximum(rms**2 - floor**2, 0.0))

    per_window = []
    for ti, tr in enumerate(rep.trajs):
        for k in np.flatnonzero(w.traj == ti):
            per_window.append({"log": tr.log.meta.get("source", f"log{ti}"), "t0": float(tr.log.time[w.start[k]]),
                               "rms": float(np.sqrt(np.sum(r[k] ** 2) / (mask[k].sum() * n)))})
    regimes = regime_breakdown(rep, r)

    per_joint = {}
    bands = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0])
    bands = bands[bands < 0.25 / dt]
    for j, name in enumerate(names):
        lags_real, lags_sim, lags_gap, freq = [], [], [], []
        for tr, q_sim in zip(rep.trajs, open_loop):
            cols = np.flatnonzero((tr.model.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT))
                                  & (tr.model.actuator_trnid[:, 0] == tr.model.joint(name).id))
            if not len(cols):
                continue
            u = tr.ctrl[::tr.nsub, cols[0]]
            lags_real.append(lag_seconds(u, tr.log.qpos[:, j], dt))
            lags_sim.append(lag_seconds(u, q_sim[:, j], dt))
            lags_gap.append(lag_seconds(q_sim[:, j], tr.log.qpos[:, j], dt))
            if len(u) * dt >= 8.0:
                real = frequency_response(u, tr.log.qpos[:, j], dt, bands)
                sim = frequency_response(u, q_sim[:, j], dt, bands)
                freq.append([{"f_hz": a["f_hz"], "gain_ratio": a["gain"] / max(b["gain"], 1e-12),
                              "phase_diff_deg": a["phase_deg"] - b["phase_deg"],
                              "coherence": min(a["coherence"], b["coherence"])} for a, b in zip(real, sim)])
        per_joint[name] = {
            "rms_pos": float(rms[j]), "rms_vel": float(rms_vel[j]), "floor": float(floor[j]),
            "excess": float(excess[j]),
            "lag_real_vs_command_s": _nanmean(lags_real), "lag_sim_vs_command_s": _nanmean(lags_sim),
            "lag_real_vs_sim_s": _nanmean(lags_gap),
            "frequency": freq[0] if freq else [],
        }
    worst = names[int(np.argmax(excess))]
    return {"per_joint": per_joint, "worst_joint": worst, "regimes": regimes, "per_window": per_window,
            "overall_rms": float(np.sqrt(np.mean(rms**2)))}


def _nanmean(values: list[float]) -> float | None:
    arr = np.array([v for v in values if np.isfinite(v)])
    return float(arr.mean()) if len(arr) else None
