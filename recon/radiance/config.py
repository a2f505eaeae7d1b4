"""Stage I's settings: its own few, and the small configs of its components nested in them,
each defined beside its component. A setting is named by its dotted path from here
(``densify.grad_threshold``; recon/settings.py reads, replaces and describes them)."""

from __future__ import annotations

from dataclasses import dataclass

from evcap.errors import InputError
from evcap.recon.events.loss import EventLossConfig
from evcap.recon.events.windows import WindowsConfig
from evcap.recon.radiance.densify import DensifyConfig
from evcap.recon.radiance.pose_refinement import PoseRefinementConfig
from evcap.recon.radiance.terms import LossConfig
from evcap.recon.scene.event_stereo import StereoConfig
from evcap.recon.scene.gaussians import BackgroundConfig, LearningRates
from evcap.recon.scene.support_plane import SupportConfig


def _check_scale(name: str, value: float) -> None:
    if not 0 < value <= 4:
        raise InputError(f"{name} is a render scale in (0, 4]; 1 is the sensor's")


@dataclass(frozen=True)
class InitConfig:
    """Stage I's first Gaussians."""

    gaussians: int = 5000
    """How many: random points inside the volume the cameras look at, but for the shares
    below."""
    on_points: float = 0.0
    """The share of them started on structure from motion's points instead, when the poses
    come with them (`evcap poses` writes them beside the poses)."""
    on_events: float = 0.0
    """The share started on the points the events' multi-view stereo finds (fewer when it
    finds fewer: none is then drawn at random in their place)."""
    stereo: StereoConfig = StereoConfig()
    """The events' multi-view stereo."""
    on_support: float = 0.0
    """The share started as flat discs on the plane the stereo's points stand on (a floor, a
    table: recon/scene/support_plane.py), taken from the shares above, when one is found; the
    mean alpha (loss.alpha) then asks the pixels whose rays meet it, inside the outline of its
    marks, to be opaque. Not sought where the background is known (background.known): that
    backdrop is seen wherever the object is not."""
    support: SupportConfig = SupportConfig()
    """Finding that plane."""
    size_px: float = 1.0
    """Their largest starting size (sigma), in render pixels."""

    def __post_init__(self) -> None:
        if self.gaussians < 1 or self.size_px <= 0:
            raise InputError("init.gaussians must be at least 1 and init.size_px above 0")
        if not all(0 <= s <= 1 for s in (self.on_points, self.on_events, self.on_support)):
            raise InputError(
                "init.on_points, init.on_events and init.on_support are shares of "
                "init.gaussians, in [0, 1]"
            )
        if self.on_points + self.on_events > 1:
            raise InputError(
                "init.on_points and init.on_events share init.gaussians: at most 1 together"
            )


@dataclass(frozen=True)
class CoarseConfig:
    """Coarse to fine: the run's first part renders at a coarser scale."""

    until: float = 0.0
    """The fraction of the run, at its start, rendered at ``resolution`` (0: none)."""
    resolution: float = 0.25
    """Its render scale, relative to the sensor."""

    def __post_init__(self) -> None:
        if not 0 <= self.until <= 1:
            raise InputError("coarse.until is a fraction of the run, in [0, 1]")
        _check_scale("coarse.resolution", self.resolution)


@dataclass(frozen=True)
class RadianceConfig:
    """Stage I: the event-supervised Gaussian radiance field."""

    iterations: int = 1000
    """Optimisation steps."""
    resolution: float = 0.5
    """The render scale, relative to the sensor (1: its pixels)."""
    sh_degree: int = 1
    """The view dependence of the Gaussians' radiance (0..3)."""
    surfels: bool = False
    """Each Gaussian a flat disc whose alpha and depth each pixel's ray takes where it meets
    it (2DGS; recon/raster/surfels.py), not a projected 3D Gaussian: a surface's depth exact
    across a tilted disc, outlines as sharp as the discs. Their third scale is not used (held
    at a hundredth of the smaller of the other two from the start)."""
    coarse: CoarseConfig = CoarseConfig()
    """Coarse to fine."""
    init: InitConfig = InitConfig()
    """The first Gaussians."""
    windows: WindowsConfig = WindowsConfig()
    """The events' time grid and the windows a step draws."""
    event_loss: EventLossConfig = EventLossConfig()
    """How the rendered change is compared with the events."""
    loss: LossConfig = LossConfig()
    """The loss's other terms."""
    lr: LearningRates = LearningRates()
    """The learning rates."""
    densify: DensifyConfig = DensifyConfig()
    """Densification (3DGS's adaptive density control)."""
    background: BackgroundConfig = BackgroundConfig()
    """The distant background."""
    poses: PoseRefinementConfig = PoseRefinementConfig()
    """The trajectory's refinement by the events."""

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise InputError("stage1.iterations must be at least 1")
        _check_scale("resolution", self.resolution)
        if not 0 <= self.sh_degree <= 3:
            raise InputError("sh_degree must be 0..3")
