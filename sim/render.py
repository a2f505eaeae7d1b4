"""The ground-truth renderer: ray-cast surfaces shaded with Lambert + GGX (metallic 0) under
the environment, the sun and point lights.

What a pixel sees: the first surface along its ray (through the distorted camera model), or
the environment. The environment's light is integrated by Monte Carlo on fixed stratified sets
(evcap.sim.integrals), not by the reconstruction's approximations: diffuse light per vertex
through cosine-weighted rays (so it costs nothing per frame); with ``lighting.shadows`` the
rays test occlusion (visibility), and with ``lighting.indirect`` the occluded ones bring the
diffuse light of the surface they hit (one bounce: color bleeding). Specular light is
integrated per pixel over GGX's visible normals, each sample's visibility read from the rays
of the triangle's vertices. The sun and point lights are exact per pixel, with a shadow ray
each when shadows are on. Surfaces are two-sided (a back face is shaded with its normal
flipped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from evcap.images import read_image_linear
from evcap.sim import integrals
from evcap.sim.camera import Camera
from evcap.sim.lighting import Environment, ggx_specular
from evcap.sim.meshes import build_mesh
from evcap.sim.raytrace import Bvh
from evcap.sim.scene import Material, Scene

SHADOW_BIAS = 1e-4  # scene units: shadow rays start this far off the surface
# what a render holds changes with this (2: the environment by Monte Carlo; 3: the relighting
# light has a glow from one side); sessions record it
RENDERER_VERSION = 3


@dataclass
class RenderResult:
    """What the renderer gives for a set of pixels (flat indices into H x W)."""

    radiance: np.ndarray  # [P, 3] linear RGB
    depth: np.ndarray  # [P] z in the camera frame; 0 where no surface
    normal: np.ndarray  # [P, 3] in the camera frame (OpenCV axes); 0 where no surface
    base_color: np.ndarray  # [P, 3]; 0 where no surface
    roughness: np.ndarray  # [P]; 0 where no surface
    hit: np.ndarray  # [P] bool
    # [P] direct irradiance received / direct irradiance if nothing blocked (environment without
    # the bounce, sun, point lights): 1 where unshadowed; 0 where no surface
    visibility: np.ndarray
    indirect: np.ndarray  # [P, 3] radiance added by the one bounce of diffuse light
    # when the render left the environment's specular light out of the radiance: what it
    # depends on at each hit (Renderer.environment_specular adds it); None when it is in
    specular_inputs: SpecularInputs | None = None


@dataclass
class SpecularInputs:
    """What the environment's specular light depends on, at the hits ``rows`` of a render."""

    rows: np.ndarray  # [H] indices into the render's pixels
    normal: np.ndarray  # [H, 3] world frame, facing the viewer
    view: np.ndarray  # [H, 3] unit direction to the viewer
    roughness: np.ndarray  # [H]
    triangle: np.ndarray  # [H, 3] vertex indices of the triangle hit
    weights: np.ndarray  # [H, 3] barycentric weights of the hit
    obj: np.ndarray  # [H] object index
    point: np.ndarray  # [H, 3] the hit, world frame
    distance: np.ndarray  # [H] from the ray's origin to the hit

    def take(self, sel: np.ndarray) -> SpecularInputs:
        """The inputs of the hits ``sel`` (a mask or indices into ``rows``)."""
        return SpecularInputs(
            *(getattr(self, k)[sel] for k in self.__dataclass_fields__)  # type: ignore[arg-type]
        )


def _no_hits() -> SpecularInputs:
    none = np.zeros((0, 3))
    index = np.zeros((0, 3), np.int64)
    return SpecularInputs(
        index[:, 0], none, none, none[:, 0], index, none, index[:, 0], none, none[:, 0]
    )


def _noise(uv: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth value noise in 0..1 (3 octaves), periodic in the unit square."""
    rng = np.random.default_rng(seed)
    total, amp, norm = np.zeros(len(uv)), 1.0, 0.0
    for octave in range(3):
        n = max(2, int(scale * 2**octave))
        lattice = rng.random((n, n))
        x, y = uv[:, 0] % 1 * n, uv[:, 1] % 1 * n
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        x0, y0, x1, y1 = x0 % n, y0 % n, (x0 + 1) % n, (y0 + 1) % n
        v = (lattice[y0, x0] * (1 - fx) + lattice[y0, x1] * fx) * (1 - fy) + (
            lattice[y1, x0] * (1 - fx) + lattice[y1, x1] * fx
        ) * fy
        total += amp * v
        norm += amp
        amp *= 0.5
    return total / norm


class Surfaces:
    """The materials of the scene: base color and roughness at surface points."""

    def __init__(
        self, materials: list[Material], boards: list[dict | None], object_ids, seed: int
    ) -> None:
        self.materials = materials
        self.seed = seed
        self.textures = [read_image_linear(m.texture) if m.texture else None for m in materials]
        self.roughness = np.array([m.roughness for m in materials])
        self.board_textures = {}
        for i, board in enumerate(boards):
            if board is not None:
                self.board_textures[i] = charuco_texture(board)

    def base_color(self, material: np.ndarray, obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
        out = np.zeros((len(material), 3))
        for m in np.unique(material):
            sel = material == m
            mat = self.materials[m]
            color = np.broadcast_to(np.asarray(mat.base_color), (int(sel.sum()), 3)).copy()
            if self.textures[m] is not None:
                color = _bilinear(self.textures[m], uv[sel])
            elif mat.procedural is not None:
                color = _procedural(mat.procedural, uv[sel], color, self.seed + int(m))
            out[sel] = color
        for o, texture in self.board_textures.items():
            sel = obj == o
            if sel.any():
                out[sel] = _bilinear(texture, uv[sel], wrap=False)
        return out


def _bilinear(img: np.ndarray, uv: np.ndarray, wrap: bool = True) -> np.ndarray:
    """[N, C] the image [H, W, C] at texture coordinates ``uv`` [N, 2] (0..1, v down), bilinear;
    ``wrap``: repeat the image (else clamp to its edge)."""
    out = np.empty((len(uv), img.shape[2]))
    _bilinear_into(np.ascontiguousarray(img, np.float64), np.ascontiguousarray(uv), wrap, out)
    return out


@numba.njit(cache=True, parallel=True)
def _bilinear_into(img, uv, wrap, out):  # pragma: no cover - compiled
    h, w = img.shape[0], img.shape[1]
    for i in numba.prange(uv.shape[0]):
        x, y = uv[i, 0] * w - 0.5, uv[i, 1] * h - 0.5
        if not wrap:
            x, y = min(max(x, 0.0), w - 1.0), min(max(y, 0.0), h - 1.0)
        fx0, fy0 = np.floor(x), np.floor(y)
        fx, fy = x - fx0, y - fy0
        x0, y0 = int(fx0) % w, int(fy0) % h
        x1, y1 = (x0 + 1) % w, (y0 + 1) % h
        for c in range(img.shape[2]):
            out[i, c] = (img[y0, x0, c] * (1 - fx) + img[y0, x1, c] * fx) * (1 - fy) + (
                img[y1, x0, c] * (1 - fx) + img[y1, x1, c] * fx
            ) * fy


def _procedural(p: dict, uv: np.ndarray, base: np.ndarray, seed: int) -> np.ndarray:
    colors = np.asarray(p.get("colors", [base[0].tolist(), [0.1, 0.1, 0.1]]), np.float64)
    scale = float(p.get("scale", 8.0))
    kind = p["kind"]
    if kind == "checker":
        k = ((np.floor(uv[:, 0] * scale) + np.floor(uv[:, 1] * scale)) % 2).astype(int)
        return colors[k % len(colors)]
    if kind == "stripes":
        k = (np.floor(uv[:, 0] * scale) % len(colors)).astype(int)
        return colors[k]
    t = _noise(uv, scale, seed)[:, None]  # noise: a blend between the first two colors
    return colors[0] * (1 - t) + colors[1] * t


def charuco_texture(board: dict, pixels_per_square: int = 64) -> np.ndarray:
    """The board's image (linear albedo: black 0.03, white 0.85), margins included."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board["dictionary"]))
    cb = cv2.aruco.CharucoBoard(
        (board["squares_x"], board["squares_y"]),
        board["square_length"],
        board["marker_length"],
        dictionary,
    )
    scale = pixels_per_square / board["square_length"]
    size = (int(round(board["width"] * scale)), int(round(board["height"] * scale)))
    margin = int(round(board["margin"] * scale))
    img = cb.generateImage(size, marginSize=margin, borderBits=1).astype(np.float64) / 255
    albedo = 0.03 + 0.82 * img
    return np.repeat(albedo[..., None], 3, axis=2)


class Renderer:
    """Renders the scene for the camera at any pose."""

    def __init__(self, scene: Scene, *, progress=None) -> None:
        self.scene = scene
        self.mesh, self.material_names, self.boards = build_mesh(scene)
        m = self.mesh
        self.bvh = Bvh(m.vertices, m.faces)
        self.env = Environment(scene.lighting)
        self.camera = Camera(scene.camera)
        self.surfaces = Surfaces(
            [scene.materials[n] for n in self.material_names], self.boards, m.object_id, scene.seed
        )
        self.lights = [
            (
                np.asarray(p["position"], np.float64),
                np.broadcast_to(np.asarray(p.get("intensity", 1.0), np.float64), (3,)),
            )
            for p in scene.lighting.points
        ]
        # float32 once here: specular_environment reads it in float32 (half the memory its reads
        # wait on) and would otherwise copy the whole table on each of its thousands of calls
        self.sky_table = self.env.table().astype(np.float32)
        self._bake(progress)

    # -- per-vertex diffuse light ----------------------------------------------------------------

    def _bake(self, progress) -> None:
        """Environment irradiance (with visibility and one bounce when asked) per vertex."""
        m, light = self.mesh, self.scene.lighting
        self.cells = integrals.cell_grid(light.samples)
        local = integrals.cosine_cells(*self.cells)  # [C, 3]
        n_vert, n_cells = len(m.vertices), len(local)
        self.vertex_frames = integrals.frames(m.normals)
        cast = light.shadows or light.indirect
        # which cells' rays reach the sky: the specular integral reads it too
        self.vertex_open = np.ones((n_vert, n_cells), np.bool_) if cast else None
        env = np.zeros((n_vert, 3))
        unshadowed = np.zeros((n_vert, 3))
        hits = []
        chunk = max(1, 262_144 // n_cells)
        for a in range(0, n_vert, chunk):
            b = min(a + chunk, n_vert)
            dirs = np.einsum("ci,vij->vcj", local, self.vertex_frames[a:b])  # [v, C, 3]
            sky = self.env.radiance(dirs.reshape(-1, 3)).reshape(b - a, n_cells, 3)
            unshadowed[a:b] = sky.mean(1) * np.pi
            if cast:
                o = np.repeat(m.vertices[a:b] + m.normals[a:b] * SHADOW_BIAS, n_cells, axis=0)
                t, face, u, v = self.bvh.closest(o, dirs.reshape(-1, 3))
                blocked = (face >= 0).reshape(b - a, n_cells)
                self.vertex_open[a:b] = ~blocked
                hits.append(tuple(x.reshape(b - a, n_cells) for x in (face, u, v)))
                if light.shadows:
                    sky = sky * ~blocked[..., None]
            env[a:b] = sky.mean(1) * np.pi
            if progress:
                progress(b, n_vert)
        # the shadow factor of the ground truth (RenderResult.visibility) needs the unshadowed too
        self.vertex_env, self.vertex_env_unshadowed = env, unshadowed
        self.vertex_bounce = np.zeros((n_vert, 3))
        self.vertex_irradiance = env
        if light.indirect:
            direct = env + self._point_irradiance(m.vertices, m.normals, shadows=light.shadows)
            bounce = np.zeros((n_vert, 3))
            for a, (face, u, v) in zip(range(0, n_vert, chunk), hits, strict=True):
                sel = face >= 0
                f, uu, vv = face[sel], u[sel], v[sel]
                w = np.stack([1 - uu - vv, uu, vv], 1)
                tri = m.faces[f]
                e_hit = (direct[tri] * w[..., None]).sum(1)
                uv = (m.uvs[tri] * w[..., None]).sum(1)
                albedo = self.surfaces.base_color(m.material[f], m.object_id[f], uv)
                rows = np.nonzero(sel)[0] + a
                # cosine-weighted: each cell carries pi / C of the irradiance
                np.add.at(bounce, rows, albedo / np.pi * e_hit * (np.pi / n_cells))
            self.vertex_irradiance = env + bounce
            self.vertex_bounce = bounce
        self.vertex_table = np.ascontiguousarray(
            np.concatenate(
                [
                    m.normals,
                    m.uvs,
                    self.vertex_irradiance,
                    self.vertex_env,
                    self.vertex_env_unshadowed,
                    self.vertex_bounce,
                ],
                axis=1,
            ),
            np.float64,
        )

    def _point_irradiance(self, x: np.ndarray, n: np.ndarray, shadows: bool) -> np.ndarray:
        """Irradiance from the sun and point lights at points x with normals n."""
        return self._point_irradiance_both(x, n, shadows)[0]

    def _point_irradiance_both(
        self, x: np.ndarray, n: np.ndarray, shadows: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """(irradiance from the sun and point lights at points x with normals n, the same
        if nothing blocked the lights)."""
        out = np.zeros((len(x), 3))
        unshadowed = np.zeros((len(x), 3))
        for direction, irradiance, distance in self._light_dirs(x):
            ndl = np.clip((n * direction).sum(1), 0, None)
            lit = ndl > 0
            if shadows and lit.any():
                lit[lit] = ~self.bvh.occluded(
                    x[lit] + n[lit] * SHADOW_BIAS, direction[lit], distance[lit] - 2 * SHADOW_BIAS
                )
            out += irradiance * (ndl * lit)[:, None]
            unshadowed += irradiance * ndl[:, None]
        return out, unshadowed

    def _light_dirs(self, x: np.ndarray):
        """(unit direction to the light [N, 3], irradiance at normal incidence [N, 3],
        distance [N]) for the sun and each point light."""
        if self.env.sun_irradiance.any():
            d = np.broadcast_to(self.env.sun_direction, x.shape)
            yield d, self.env.sun_irradiance * self.env.scale, np.full(len(x), np.inf)
        for position, intensity in self.lights:
            v = position - x
            dist = np.linalg.norm(v, axis=1)
            yield (
                v / np.maximum(dist, 1e-12)[:, None],
                intensity / np.maximum(dist, 1e-12)[:, None] ** 2,
                dist,
            )

    # -- rendering ---------------------------------------------------------------------------------

    def render(
        self,
        T_world_cam: np.ndarray,
        pixels: np.ndarray | None = None,
        *,
        specular: bool = True,
    ) -> RenderResult:
        """Render the pixels (flat indices; None: all) for the camera at ``T_world_cam``;
        ``specular``: as in render_rays."""
        rays = self.camera.rays() if pixels is None else self.camera.rays()[pixels]
        rot, origin = T_world_cam[:3, :3], T_world_cam[:3, 3]
        result = self.render_rays(
            np.broadcast_to(origin, rays.shape), rays @ rot.T, rays[:, 2], specular=specular
        )
        result.normal = result.normal @ rot  # into the camera frame
        return result

    def render_rays(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        ray_z: np.ndarray | None = None,
        *,
        specular: bool = True,
    ) -> RenderResult:
        """Render rays from their own origins (each pixel may come from a camera at another
        time): the simulator's refinements. Normals stay in the world frame; depth is the
        distance along the ray times ``ray_z`` (the ray's z in its camera frame), if given.
        ``specular`` False: the environment's specular light is left out of the radiance, and
        the result's specular_inputs say what it depends on."""
        t, face, u, v = self.bvh.closest(origins, dirs)
        origin = origins[face >= 0] if len(origins) else origins
        n_px = len(dirs)
        hit = face >= 0
        radiance = np.zeros((n_px, 3))
        normal = np.zeros((n_px, 3))
        base = np.zeros((n_px, 3))
        rough = np.zeros(n_px)
        depth = np.zeros(n_px)
        light_visibility = np.zeros(n_px)
        indirect = np.zeros((n_px, 3))
        inputs = _no_hits()
        if (~hit).any():
            radiance[~hit] = self.env.background(dirs[~hit])
        if hit.any():
            m, f = self.mesh, face[hit]
            w = np.stack([1 - u[hit] - v[hit], u[hit], v[hit]], 1)
            tri = m.faces[f]
            x = origin + dirs[hit] * t[hit, None]
            # every per-vertex quantity at the hits, in one compiled pass
            at_hit = _blend(self.vertex_table, tri, w)
            n, uv, irradiance, received, unblocked, bounce = np.split(
                at_hit, [3, 5, 8, 11, 14], axis=1
            )
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            view = -dirs[hit]
            flip = (n * view).sum(1) < 0  # two-sided
            n[flip] = -n[flip]
            albedo = self.surfaces.base_color(m.material[f], m.object_id[f], uv)
            r = self.surfaces.roughness[m.material[f]]
            shadows = self.scene.lighting.shadows
            points, points_unshadowed = self._point_irradiance_both(x, n, shadows)
            irradiance = irradiance + points
            color = albedo / np.pi * irradiance
            received = (received + points).sum(1)
            unblocked = (unblocked + points_unshadowed).sum(1)
            dark = unblocked <= 1e-12
            # clip: the ratio may pass 1 by rounding
            light_visibility[hit] = np.where(
                dark, 1.0, np.clip(received / np.where(dark, 1.0, unblocked), 0, 1)
            )
            indirect[hit] = albedo / np.pi * bounce
            inputs = SpecularInputs(
                np.flatnonzero(hit), n, view, r, tri, w, m.object_id[f], x, t[hit]
            )
            if specular:
                color += self.environment_specular(inputs)
            for direction, irr, distance in self._light_dirs(x):
                spec = ggx_specular(n, view, direction, r)
                if shadows:
                    lit = spec > 0
                    spec[lit] *= ~self.bvh.occluded(
                        x[lit] + n[lit] * SHADOW_BIAS,
                        direction[lit],
                        distance[lit] - 2 * SHADOW_BIAS,
                    )
                color += spec[:, None] * irr
            radiance[hit] = color
            normal[hit] = n
            base[hit] = albedo
            rough[hit] = r
            depth[hit] = t[hit] * (ray_z[hit] if ray_z is not None else 1.0)
        return RenderResult(
            radiance,
            depth,
            normal,
            base,
            rough,
            hit,
            light_visibility,
            indirect,
            None if specular else inputs,
        )

    def environment_specular(self, inputs: SpecularInputs) -> np.ndarray:
        """[H, 3] the environment's specular light at the hits (integrals.specular_environment,
        the sky's visibility read from the bake when shadows are on)."""
        sky_open = None
        if self.scene.lighting.shadows:
            sky_open = (
                inputs.triangle,
                inputs.weights,
                self.vertex_frames,
                self.vertex_open,
                *self.cells,
            )
        return integrals.specular_environment(
            self.sky_table,
            inputs.normal,
            inputs.view,
            inputs.roughness,
            self.scene.lighting.specular_side,
            sky_open,
        )

    def render_full(self, T_world_cam: np.ndarray) -> dict[str, np.ndarray]:
        """All pixels, as images: radiance [H, W, 3], depth, normal, base_color, roughness,
        visibility, indirect."""
        h, w = self.camera.height, self.camera.width
        r = self.render(T_world_cam)
        return {
            "radiance": r.radiance.reshape(h, w, 3).astype(np.float32),
            "depth": r.depth.reshape(h, w).astype(np.float32),
            "normal": r.normal.reshape(h, w, 3).astype(np.float32),
            "base_color": r.base_color.reshape(h, w, 3).astype(np.float32),
            "roughness": r.roughness.reshape(h, w).astype(np.float32),
            "visibility": r.visibility.reshape(h, w).astype(np.float32),
            "indirect": r.indirect.reshape(h, w, 3).astype(np.float32),
        }


@numba.njit(cache=True, parallel=True)
def _blend(table, tri, w):  # pragma: no cover - compiled
    """[H, K] the rows of ``table`` [V, K] at the triangles' vertices, weighted by ``w``."""
    out = np.empty((tri.shape[0], table.shape[1]))
    for i in numba.prange(tri.shape[0]):
        a, b, c = tri[i, 0], tri[i, 1], tri[i, 2]
        wa, wb, wc = w[i, 0], w[i, 1], w[i, 2]
        for k in range(table.shape[1]):
            out[i, k] = table[a, k] * wa + table[b, k] * wb + table[c, k] * wc
    return out
