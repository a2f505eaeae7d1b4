"""The event-derived edge map: flow by contrast maximisation, and the map's hard cases."""

import numpy as np
import pytest

from evcap.edge_maps import edge_map, variance_gain

pytestmark = pytest.mark.filterwarnings("error")

W, H = 96, 72
T0 = 1_000_000
SLICE_US = 20_000
TWO_DAYS_US = 172_800_000_000
V1 = np.array([300.0, -120.0])
V2 = np.array([-220.0, 160.0])


def patch_centre(c, r, cols=4, rows=3):
    return np.array([(c + 0.5) * W / cols - 0.5, (r + 0.5) * H / rows - 0.5])


def triangles(centres, velocities, seed, radius=9.0):
    """The edges (a, b, velocity) of triangle outlines at random angles, one per centre.

    Triangles, not lone straight edges: an edge's motion along itself is invisible (the aperture
    problem), so a patch needs edges of two directions for its velocity to be defined."""
    rng = np.random.default_rng(seed)
    edges = []
    for centre, v in zip(centres, velocities, strict=True):
        angles = rng.uniform(0, 2 * np.pi) + np.arange(3) * 2 * np.pi / 3
        corners = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        edges += [(a, b, v) for a, b in zip(corners, np.roll(corners, 1, axis=0), strict=True)]
    return edges


def scene(edges, t0=T0, t_ref=T0 + SLICE_US // 2, seed=0, per_edge=300, noise=15):
    """Events of straight edges (a, b at t_ref, each moving at its velocity) over one 20 ms
    slice, plus uniform noise events; and the edges' pixels at t_ref [H, W] bool.

    As a sensor sees them: at pixel centres, each at the time the moving edge crosses that pixel
    (some 800 events for a triangle of `triangles`)."""
    rng = np.random.default_rng(seed + 1000)
    xy, t = [], []
    on_edge = np.zeros((H, W), bool)
    for a, b, v in edges:
        normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
        # a point of the edge at a random time in the slice, then the pixel it is on and the
        # time at which the edge crosses that pixel's centre
        ti = rng.integers(t0, t0 + SLICE_US, per_edge)
        p = a + rng.random((per_edge, 1)) * (b - a) + ((ti - t_ref) * 1e-6)[:, None] * v
        pixel = np.round(p)
        ti = t_ref + np.round((pixel - a) @ normal / (v @ normal) * 1e6).astype(np.int64)
        keep = (ti >= t0) & (ti < t0 + SLICE_US)
        xy.append(pixel[keep])
        t.append(ti[keep])
        line = np.round(a + np.linspace(0, 1, 100)[:, None] * (b - a)).astype(int)
        on_edge[line[:, 1], line[:, 0]] = True
    xy.append(np.round(rng.uniform([0, 0], [W - 1, H - 1], (noise, 2))))
    t.append(rng.integers(t0, t0 + SLICE_US, noise))
    xy, t = np.concatenate(xy), np.concatenate(t)
    order = np.argsort(t, kind="stable")
    return xy[order], t[order], on_edge


def flow_errors(flow, truth):
    """Per patch, the error of its velocity over the truth's speed."""
    return np.linalg.norm(flow - truth, axis=-1) / np.linalg.norm(truth)


ONE_MOTION = [patch_centre(c, r) for c, r in [(0, 0), (1, 1), (2, 0), (3, 2), (0, 2), (2, 2)]]
T_MID = T0 + SLICE_US // 2


def test_flow_and_map_of_a_translating_scene():
    xy, t, on_edge = scene(triangles(ONE_MOTION, [V1] * 6, seed=0))
    m, flow = edge_map(xy, t, T_MID, W, H)
    assert m.shape == (H, W) and m.dtype == np.float32
    assert flow.shape == (3, 4, 2) and flow.dtype == np.float64
    # the patches without a triangle take the median of the others
    assert flow_errors(flow, V1).max() < 0.05
    assert m.max() == 1.0 and m.min() == 0.0
    assert m[on_edge].mean() > 5 * m[~on_edge].mean()


def test_variance_gain():
    xy, t, _ = scene(triangles(ONE_MOTION, [V1] * 6, seed=0))
    # the smear is 6.5 px over the slice, against triangles 16 px across
    assert variance_gain(xy, t, T_MID, W, H, np.broadcast_to(V1, (3, 4, 2))) > 1.3
    assert variance_gain(xy, t, T_MID, W, H, np.broadcast_to(-V1, (3, 4, 2))) < 1.0
    assert variance_gain(xy, t, T_MID, W, H, np.zeros((3, 4, 2))) == 1.0


def test_two_halves_with_their_own_motions():
    centres = [patch_centre(c, r) for r in range(3) for c in range(4)]
    velocities = [V1 if c[0] < W / 2 else V2 for c in centres]
    xy, t, _ = scene(triangles(centres, velocities, seed=1), seed=1)
    _, flow = edge_map(xy, t, T_MID, W, H)
    # a lone triangle of ~800 events pins its patch's velocity to a few %: the patches are held
    # to 15 % (the other half's velocity is ~200 % away), and their median to 5 %
    for half, truth in ((flow[:, :2], V1), (flow[:, 2:], V2)):
        assert flow_errors(half, truth).max() < 0.15
        assert flow_errors(np.median(half.reshape(-1, 2), axis=0), truth) < 0.05


def test_timestamps_two_days_in():
    t0 = TWO_DAYS_US + 123_457
    # t_ref at the start of the slice: the triangles are placed so as to stay in their patches
    centres = [c - V1 * SLICE_US * 0.5e-6 for c in ONE_MOTION]
    xy, t, on_edge = scene(triangles(centres, [V1] * 6, seed=2), t0=t0, t_ref=t0, seed=2)
    m, flow = edge_map(xy, t, t0, W, H)
    # times as float32 seconds would be off by up to 8 ms here, in a 20 ms slice (the flow's
    # precision itself is the first test's)
    assert flow_errors(flow, V1).max() < 0.08
    assert np.isfinite(m).all() and m.min() >= 0 and m.max() <= 1
    assert m[on_edge].mean() > 5 * m[~on_edge].mean()


def test_map_of_long_straight_edges():
    # a patch that sees one edge direction can only guess the flow along that edge, but that
    # part of the flow slides the edge along itself: the map stays as sharp
    ends = [((8, 10), (80, 20)), ((20, 62), (40, 8)), ((50, 60), (90, 45))]
    edges = [(np.array(a, float), np.array(b, float), V1) for a, b in ends]
    xy, t, on_edge = scene(edges, seed=3, per_edge=600)
    m, flow = edge_map(xy, t, T_MID, W, H)
    assert m.max() == 1.0 and m.min() == 0.0
    assert m[on_edge].mean() > 5 * m[~on_edge].mean()
    assert variance_gain(xy, t, T_MID, W, H, flow) > 1.3


@pytest.mark.parametrize(
    "xy, t, t_ref",
    [
        (np.zeros((0, 2)), np.zeros(0, np.int64), T0),
        (np.array([[10.3, 20.7]]), np.array([T0]), T0),
        (np.full((50, 2), 40.0), np.full(50, T0), T0),
        (np.array([[-5.0, 3.0], [200.0, 10.0], [3.0, 90.0]]), np.array([T0, T0 + 5, T0 + 9]), T0),
        (np.full((50, 2), 40.0), TWO_DAYS_US + np.arange(50) * 400, TWO_DAYS_US),
        (np.full((50, 2), 40.0), TWO_DAYS_US + np.arange(50) * 400, T0),
        (np.array([[np.nan, 1.0], [np.inf, 2.0], [1e300, 3.0], [5.0, 6.0]]), np.full(4, T0), T0),
    ],
    ids=["empty", "one", "one pixel and time", "outside", "two days", "t_ref days away", "inf"],
)
def test_degenerate_inputs_are_finite(xy, t, t_ref):
    m, flow = edge_map(xy, t, t_ref, W, H)
    assert m.shape == (H, W) and m.dtype == np.float32 and np.isfinite(m).all()
    assert m.min() >= 0 and m.max() <= 1
    assert flow.shape == (3, 4, 2) and np.isfinite(flow).all()
    assert np.isfinite(variance_gain(xy, t, t_ref, W, H, flow))
    if len(t) == 0:
        assert not m.any() and not flow.any()
