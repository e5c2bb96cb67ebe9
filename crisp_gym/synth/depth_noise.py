"""The errors of a monocular depth network, applied to exact synthetic depth: an unknown global scale,
per-frame drift, low-frequency distortion, noise growing with depth, flying pixels and holes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter, zoom

from crisp_gym.synth.camera import smooth_noise


@dataclass(frozen=True)
class DepthNoise:
    """Errors of a monocular depth network (applied in this order).

    Attributes:
        scale_range: the unknown global scale s is drawn log-uniformly from this range; the
            input depth and camera translations are the true ones divided by s (metric = s × input).
        scale_drift: standard deviation over the clip of the smooth per-frame scale error
            (relative; its mean over the clip is 0, so s stays the clip's true scale).
        drift_seconds: time scale of that drift (s).
        distortion: RMS of a low-frequency multiplicative distortion of each depth map (relative).
        distortion_seconds: period over which the distortion pattern changes (s).
        pixel_noise: per-pixel Gaussian noise, σ = pixel_noise × depth² (1/m): it grows with depth.
        flying_pixels: probability that a pixel at a depth edge takes a depth between the
            foreground and the background (a "flying pixel").
        edge_jump: a relative depth jump within edge_width pixels that counts as an edge.
        edge_width: how many pixels from an edge flying pixels reach.
        holes: fraction of pixels lost in blob-shaped holes (depth 0).
        float16: store depth as float16, as MegaSAM does.
    """

    scale_range: tuple[float, float] = (0.5, 2.0)
    scale_drift: float = 0.02
    drift_seconds: float = 1.0
    distortion: float = 0.01
    distortion_seconds: float = 4.0
    pixel_noise: float = 0.001
    flying_pixels: float = 0.5
    edge_jump: float = 0.05
    edge_width: int = 1
    holes: float = 0.0
    float16: bool = True

    def __post_init__(self) -> None:
        lo, hi = self.scale_range
        if not 0 < lo <= hi:
            raise ValueError(f"scale_range must be 0 < low <= high, got {self.scale_range}")
        for name in ("scale_drift", "distortion", "pixel_noise", "edge_jump"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.flying_pixels <= 1 or not 0 <= self.holes < 1:
            raise ValueError(f"flying_pixels must be in [0, 1] and holes in [0, 1), got "
                             f"{self.flying_pixels}, {self.holes}")
        if self.edge_width < 1 or self.drift_seconds <= 0 or self.distortion_seconds <= 0:
            raise ValueError("edge_width, drift_seconds and distortion_seconds must be positive")

    @classmethod
    def clean(cls) -> DepthNoise:
        """Exact metric depth: no scale, drift, distortion, noise, flying pixels or holes."""
        return cls(scale_range=(1.0, 1.0), scale_drift=0.0, distortion=0.0, pixel_noise=0.0,
                   flying_pixels=0.0, holes=0.0, float16=False)


@dataclass
class NoiseModel:
    """Per-clip draws of :class:`DepthNoise`, applied frame by frame."""

    cfg: DepthNoise
    rng: np.random.Generator
    num_frames: int
    fps: float
    width: int
    height: int

    def __post_init__(self) -> None:
        lo, hi = self.cfg.scale_range
        self.scale = float(np.exp(self.rng.uniform(np.log(lo), np.log(hi))))
        drift = smooth_noise(self.rng, self.num_frames, 1, self.cfg.drift_seconds * self.fps)[:, 0]
        drift -= drift.mean()  # the clip's mean scale is the true one
        spread = drift.std()  # normalised over the clip: a short clip drifts as much as a long one
        self.drift = 1.0 + self.cfg.scale_drift * (drift / spread if spread > 1e-12 else drift)
        terms = 4
        self._freq = self.rng.uniform(-1.0, 1.0, (terms, 2))  # cycles per image
        self._phase = self.rng.uniform(0, 2 * np.pi, terms)
        self._omega = 2 * np.pi / self.cfg.distortion_seconds * self.rng.uniform(0.5, 1.5, terms)
        self._amp = self.cfg.distortion / np.sqrt(terms / 2) * self.rng.choice([-1.0, 1.0], terms)
        self._u = np.arange(self.width) / self.width
        self._v = np.arange(self.height) / self.height

    def apply(self, depth: np.ndarray, k: int) -> np.ndarray:
        """Frame ``k``'s true metric depth (0 = no hit) → its noisy depth divided by the scale."""
        cfg, rng = self.cfg, self.rng
        valid = depth > 0
        d = depth.astype(np.float32) * np.float32(self.drift[k])
        if cfg.distortion > 0:
            # Σ amp cos(a_k(v) + b_k(u)) = Σ amp (cos a cos b − sin a sin b): separable rank-2 terms
            a = 2 * np.pi * np.outer(self._v, self._freq[:, 1]) + self._phase + self._omega * k / self.fps
            b = 2 * np.pi * np.outer(self._freq[:, 0], self._u)
            rows = np.concatenate([self._amp * np.cos(a), -self._amp * np.sin(a)], axis=1).astype(np.float32)
            cols = np.concatenate([np.cos(b), np.sin(b)], axis=0).astype(np.float32)
            d *= 1.0 + np.einsum("hk,kw->hw", rows, cols)
        if cfg.flying_pixels > 0:
            size = 2 * cfg.edge_width + 1
            lo = minimum_filter(np.where(valid, d, np.inf), size)
            hi = maximum_filter(np.where(valid, d, 0.0), size)
            edge = valid & np.isfinite(lo) & (hi - lo > cfg.edge_jump * lo)
            fly = edge & (rng.random(d.shape, dtype=np.float32) < cfg.flying_pixels)
            d[fly] = lo[fly] + rng.random(int(fly.sum()), dtype=np.float32) * (hi[fly] - lo[fly])
        if cfg.pixel_noise > 0:
            d += rng.standard_normal(d.shape, dtype=np.float32) * np.float32(cfg.pixel_noise) * d * d
        d = np.where(valid & (d > 0), d, 0.0)
        if cfg.holes > 0:
            coarse = rng.standard_normal((self.height // 16 + 2, self.width // 16 + 2))
            blobs = zoom(coarse, (self.height / coarse.shape[0], self.width / coarse.shape[1]), order=1)
            blobs = blobs[:self.height, :self.width]
            d[blobs < np.quantile(blobs, cfg.holes)] = 0.0
        return d / np.float32(self.scale)
