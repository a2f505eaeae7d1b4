"""The camera's trajectory refined by stage I's event loss (issue 22).

Each keyframe (one every ``pose_keyframe_ms`` along the recording) carries a small rigid
correction: a rotation about the camera's centre (an axis-angle vector in world axes, radians)
and a shift of the centre (in units of the scene's extent). Between keyframes the corrections
are interpolated linearly, so the corrected path stays as smooth as the one it corrects. The
gauge is fixed after every step: the first keyframe is not corrected, and the shifts keep the
path's scale (no part of them stretches the path about its first centre), since the events
cannot tell a larger scene seen from further away. The rasterizers differentiate the camera,
so the event loss's gradient reaches the corrections through the corrected poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import assert_never

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon.config import REFINE_POSES, RefinePoses
from evcap.records import Poses

# sources of poses `auto` refines: those evcap estimated
ESTIMATED = ("evcap poses", "evcap reconstruct")


@dataclass(frozen=True)
class PoseRefinementConfig:
    """The trajectory refined by the event loss: a correction per keyframe."""

    refine: RefinePoses = "auto"
    """"on", "off", or "auto": when evcap estimated the poses (`evcap poses`)."""
    keyframe_ms: float = 100.0
    """One keyframe every this many ms along the recording."""
    start: float = 0.3
    """The fraction of the run after which the corrections are learnt."""
    lr_rotation: float = 1e-4
    """Adam's rate of the rotations (radians); it decays tenfold by the end of the run."""
    lr_shift: float = 1e-4
    """Adam's rate of the shifts (fractions of the scene's extent); it decays tenfold."""
    smooth_weight: float = 1.0
    """The weight of the corrections' second differences along the keyframes."""

    def __post_init__(self) -> None:
        if self.refine not in REFINE_POSES:
            raise InputError(f"poses.refine must be one of {', '.join(REFINE_POSES)}")
        if not 0 <= self.start < 1 or self.keyframe_ms <= 0:
            raise InputError("poses.start is a fraction of the run, in [0, 1); keyframe_ms > 0")

    def refines(self, track: Poses) -> bool:
        """Whether the corrections are learnt for this trajectory."""
        match self.refine:
            case "on":
                return True
            case "off":
                return False
            case "auto":
                return track.source.startswith(ESTIMATED)
            case _:
                assert_never(self.refine)


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle vectors -> [..., 3, 3] rotation matrices; smooth at zero (the
    series of sin and cos to the sixth order, exact well beyond the corrections' size)."""
    theta2 = (w * w).sum(-1)[..., None, None]
    a = 1 - theta2 / 6 + theta2 * theta2 / 120 - theta2**3 / 5040
    b = 0.5 - theta2 / 24 + theta2 * theta2 / 720 - theta2**3 / 40320
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*w.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * k + b * (k @ k)


class PoseCorrections(torch.nn.Module):
    """Per-keyframe corrections of a trajectory, interpolated in time."""

    def __init__(self, track: Poses, start: int, end: int, interval_us: int, extent: float):
        super().__init__()
        count = max(int(np.ceil((end - start) / max(interval_us, 1))) + 1, 2)
        self.times = np.linspace(start, end, count).round().astype(np.int64)
        self.extent = float(extent)
        self.rotation = torch.nn.Parameter(torch.zeros(count, 3, dtype=torch.float64))
        self.shift = torch.nn.Parameter(torch.zeros(count, 3, dtype=torch.float64))
        self.base = torch.from_numpy(track.at(self.times)[:, :3, 3])  # the keyframes' centres

    def __len__(self) -> int:
        return len(self.times)

    def at(self, t_us: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """The corrections at the given times: rotations [N, 3] (rad) and shifts [N, 3]
        (scene units); constant beyond the first and last keyframes."""
        t = np.clip(np.asarray(t_us, np.int64), self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        s = torch.from_numpy(s.astype(np.float64))[:, None]
        j = torch.from_numpy(i)

        def lerp(p: torch.Tensor) -> torch.Tensor:
            # index_select: p[j]'s gradient would add the repeats in the threads' order
            return p.index_select(0, j) * (1 - s) + p.index_select(0, j + 1) * s

        return lerp(self.rotation), self.extent * lerp(self.shift)

    def apply(self, T_world_cam: np.ndarray, t_us: np.ndarray) -> torch.Tensor:
        """The transforms [N, 4, 4] at times ``t_us`` corrected (float64, differentiable)."""
        w, c = self.at(t_us)
        T = torch.from_numpy(np.asarray(T_world_cam, np.float64)).clone()
        R = exp_so3(w) @ T[:, :3, :3]
        top = torch.cat([R, (T[:, :3, 3] + c)[..., None]], -1)
        return torch.cat([top, T[:, 3:]], 1)

    def smoothness(self) -> torch.Tensor:
        """Squared second differences of the keyframes' corrections (rad, extents)."""
        if len(self) < 3:
            return self.rotation.sum() * 0
        d2 = lambda p: p[2:] - 2 * p[1:-1] + p[:-2]  # noqa: E731
        return (d2(self.rotation) ** 2).sum(1).mean() + (d2(self.shift) ** 2).sum(1).mean()

    @torch.no_grad()
    def fix_gauge(self) -> None:
        """The first keyframe uncorrected; no stretch of the path about its first centre."""
        self.rotation[0] = 0
        self.shift[0] = 0
        d = (self.base - self.base[0]) / self.extent
        norm = (d * d).sum()
        if norm > 0:
            self.shift -= ((d * self.shift).sum() / norm) * d

    def refined(self, track: Poses) -> Poses:
        """``track`` at its own times and the keyframes', corrected."""
        t = np.union1d(track.t, self.times[(self.times > track.start) & (self.times < track.end)])
        with torch.no_grad():
            T = self.apply(track.at(t), t).numpy()
        w, _ = self.at(t)
        angles = np.degrees(w.detach().norm(dim=1).numpy())
        return track.replace(
            t=t,
            T_world_cam=T,
            source=f"evcap reconstruct: refined ({track.source})",
            notes={
                "refined_from": track.source,
                "refinement_keyframes": len(self),
                "refinement_median_deg": float(np.median(angles)),
                "refinement_max_deg": float(angles.max()),
            },
        )
