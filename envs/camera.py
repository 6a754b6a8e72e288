"""An exact, fast camera for flat worlds with vertical obstacles (pure JAX, jittable, vmappable).

Why not ``mjx.ray`` per pixel: it tests every pixel against every geom in 3-D.  Our worlds are flat and
every obstacle is vertical (envs/scene.py), so the expensive part factors: with a camera whose image
plane is vertical, all pixels of one image column lie in one *vertical* half-plane, i.e. they share a
single horizontal ray.  We therefore

1. cast one 2-D ray per column against every circle (analytic ray-circle) and every oriented box (slab
   test in the box frame) -> entry distances, an [N, W] problem;
2. keep the K nearest primitives of each column (``CameraConfig.max_hits``, K passes of a min and a
   first-index-of-the-min reduction over N);
3. per pixel, intersect the pixel's ray (known slope dz/dt over horizontal distance t) with those K
   candidates in the column's vertical plane -- wall face (z within [0, h] at the entry distance), the
   capsule's top dome, a box top -- and with the ground / ceiling planes, and keep the nearest;
4. shade: class and colour of the chosen surface, ground paint looked up at the hit point (only rows
   below the horizon can see the ground, and there the hit distance is a per-pixel constant), Lambert
   term, a world-space checker texture and distance fog.

Cost per pixel is O(K + patches), per column O(N); everything is float32 and elementwise over
[H, W] / [K, W] arrays with W as the minor axis (what XLA vectorises), and the two loops over K are
``lax.scan``s so their results are materialised once (see the comment in ``render``).

Exactness.  Below the horizon a ray descends from the camera height, so at the nearest wall it is
below that obstacle's top whenever the obstacle is taller than the camera: the nearest hit is exact.
Only rays that pass over an obstacle (above the horizon, or over obstacles lower than the camera) need
what lies behind, and the K nearest entries per column cover that (K = 4 by default); a ray that passes
over K obstacles in a row and then hits a (K+1)-th is the only case drawn wrongly (as ground or sky).

Camera model ("shifted lens", keystone-free): the image plane is vertical and the principal point is
shifted so that the centre row looks ``pitch_deg`` below the horizon.  Vertical world lines stay
vertical in the image, which is what makes one 2-D ray per column exact.  Compared with a tilted
pinhole (the paper's Panda3D camera, 3.9 degrees down), image points move by less than the tilt's
keystone effect, about 1 % of the image height at the corners.  ``pixel_rays`` gives the exact ray of
every pixel, and ``mjx_ray_depth`` casts the same rays with ``mjx.ray`` as a reference.

Shapes the camera draws are exactly MuJoCo's (see the mapping in envs/scene.py): a circle is a vertical
cylinder over z in [0, h] with a hemispherical dome of the same radius on top (the capsule's top cap);
a box spans z in [0, h].  Depth is the distance along the pixel's ray (what ``mjx.ray`` returns for a
unit direction); pixels with nothing within ``far`` are background: class SKY, depth ``far``.
"""
from __future__ import annotations

import dataclasses
import math
import sys

import jax
import jax.numpy as jnp
import numpy as np

from envs.scene import CEILING, SCENE_GEOMGROUP, SKY, Scene

_BIG = 1e30  # "no hit" distance inside the computation (finite, so products never make NaN)
_PROJECTIONS = ("pinhole", "cylindrical")
_GROUND, _CEIL = -1, -2  # per-pixel surface codes besides the candidate index 0..K-1
_GATHER_PATCHES = 4  # more ground patches than this: per-pixel table look-ups instead of select chains


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Static camera description (hashable: one compiled renderer per config).

    Geometry: the camera sits ``mount_forward`` m ahead of the car centre at ``mount_height`` m and
    looks ``pitch_deg`` below the horizon (default: at the ground 6 m ahead of the car centre, the
    paper's forest camera, about 3.9 degrees).  Square pixels: the vertical field of view follows from
    ``hfov_deg`` and the aspect ratio.

    ``projection``: "pinhole" (the paper's cameras; ``hfov_deg`` below 180) or "cylindrical" (columns
    at equal angles, ``hfov_deg`` up to 360, e.g. a camera that sees beside the car; rows keep a
    constant slope per horizontal metre, so vertical lines stay vertical and the renderer's one 2-D
    ray per column stays exact).  Why offer it: a pinhole's centre pixels widen fast with the field
    of view (3.1 degrees at 120, 6.7 at 150 for 64 columns), a cylinder's all share hfov / width.
    """

    width: int = 64
    height: int = 36
    hfov_deg: float = 120.0
    projection: str = "pinhole"  # or "cylindrical" (see the class docstring)
    mount_height: float = 0.375
    mount_forward: float = 0.5
    pitch_deg: float = math.degrees(math.atan2(0.375, 5.5))
    grayscale: bool = False
    far: float = 100.0  # nothing farther is drawn (like a GL far plane)
    max_hits: int = 4  # K nearest obstacles kept per column (see the module docstring)
    # Shading: Lambert with ambient, exponential fog toward the horizon colour, a 3-D checker texture.
    light_dir: tuple[float, float, float] = (0.35, 0.5, 0.8)  # toward the light; normalised at use
    ambient: float = 0.45
    fog_distance: float = 60.0  # e-folding distance of the fog (m)
    texture_cell: float = 0.5  # checker cell size (m): makes ego-motion visible on the ground
    texture_contrast: float = 0.08
    sky_horizon_color: tuple[float, float, float] = (0.78, 0.84, 0.9)
    sky_zenith_color: tuple[float, float, float] = (0.45, 0.62, 0.85)
    ceiling_color: tuple[float, float, float] = (0.85, 0.85, 0.82)
    ceiling_light: float = 0.6  # diffuse term of the ceiling (lit from the room, not the sun)

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera resolution must be positive, got {self.width}x{self.height}")
        if self.projection not in _PROJECTIONS:
            raise ValueError(f"projection must be one of {_PROJECTIONS}, got {self.projection!r}")
        widest = 180 if self.projection == "pinhole" else 360
        if not 0 < self.hfov_deg < widest:
            raise ValueError(f"hfov_deg must be in (0, {widest}) for a {self.projection} camera, got {self.hfov_deg}")
        if self.max_hits < 1:
            raise ValueError(f"max_hits must be >= 1, got {self.max_hits}")

    @property
    def channels(self) -> int:
        return 1 if self.grayscale else 3

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return (self.height, self.width, self.channels)


# The three worlds' cameras (caps-algorithm.md section 9); scenes may override mount or shading.
FOREST_CAMERA = CameraConfig(width=64, height=36)
CITY_CAMERA = CameraConfig(width=100, height=50, grayscale=True)
HALL_CAMERA = CameraConfig(width=128, height=96)


def _image_coords(cfg: CameraConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's geometry in the car frame, as float32 numpy constants.

    Returns ``(along, across, rise)``: pixel (i, j) looks along the car-frame direction
    ``(along_j, -across_j, rise_i)`` (forward, left, up; not unit length).  Pinhole: the image plane at
    focal length 1, ``along`` = 1, ``across`` and ``rise`` the image-plane coordinates (right, up).
    Cylindrical: ``(along, across)`` = (cos, sin) of column azimuths at equal steps, and ``rise`` a
    row's slope, the same in every column.
    """
    half = math.radians(cfg.hfov_deg) / 2
    u = 2 * (np.arange(cfg.width) + 0.5) / cfg.width - 1  # -1 .. 1, left to right
    v = 1 - 2 * (np.arange(cfg.height) + 0.5) / cfg.height  # 1 .. -1, top to bottom
    tilt = math.tan(math.radians(cfg.pitch_deg))
    if cfg.projection == "pinhole":
        ax = math.tan(half)
        along, across, rise = np.ones_like(u), ax * u, ax * cfg.height / cfg.width * v - tilt
    else:  # square pixels at the image centre: a row's step in slope equals a column's step in angle
        along, across = np.cos(half * u), np.sin(half * u)
        rise = half * cfg.height / cfg.width * v - tilt
    return along.astype(np.float32), across.astype(np.float32), rise.astype(np.float32)


def camera_origin(pose: jax.Array, cfg: CameraConfig) -> jax.Array:
    """World position f32[3] of the camera for a car pose (x, y, yaw)."""
    pose = jnp.asarray(pose, jnp.float32)
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    return jnp.stack([pose[0] + cfg.mount_forward * c, pose[1] + cfg.mount_forward * s,
                      jnp.asarray(cfg.mount_height, jnp.float32)])


def pixel_rays(pose: jax.Array, cfg: CameraConfig) -> tuple[jax.Array, jax.Array]:
    """The camera model: origin f32[3] and unit world direction f32[h, w, 3] of every pixel."""
    along, across, rise = _image_coords(cfg)
    yaw = jnp.asarray(pose, jnp.float32)[2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    # Car frame: forward (along), left (-across), up (rise); rotated by yaw into the world.
    fx, fy = along, -across
    wx, wy = c * fx - s * fy, s * fx + c * fy
    d = jnp.stack([jnp.broadcast_to(wx, (cfg.height, cfg.width)), jnp.broadcast_to(wy, (cfg.height, cfg.width)),
                   jnp.broadcast_to(rise[:, None], (cfg.height, cfg.width))], -1)
    return camera_origin(pose, cfg), d / jnp.linalg.norm(d, axis=-1, keepdims=True)


# Layout note (why the code below looks the way it does): XLA on CPU vectorises along the minor axis.
# Every per-column array keeps the image width W as its minor axis and every per-pixel array is
# [H, W]; loops over primitives, candidates and patches are Python/scan loops over *major* slices with
# scalar parameters.  Slicing a small minor axis (e.g. [W, N][..., n]) made the same math ~10x slower.


def _circle_hits(cx, cy, r, cam, dx, dy):
    """Horizontal ray (from ``cam``, unit direction (dx, dy)) against circles; arrays broadcast.

    Returns entry and exit distances (entry = exit when the camera is inside: mjx.ray then sees the far
    wall), the along-ray distance ``tc`` of the centre's projection, the chord half-length and a hit flag.
    """
    rx, ry = cx - cam[0], cy - cam[1]
    tc = dx * rx + dy * ry
    chord2 = r * r - (rx * rx + ry * ry - tc * tc)
    half = jnp.sqrt(jnp.maximum(chord2, 0.0))
    t_out = tc + half
    t_in = jnp.where(tc >= half, tc - half, t_out)
    return t_in, t_out, tc, half, (r > 0) & (chord2 > 0) & (t_out >= 0)


def _box_hits(bx, by, ex, ey, yaw, cam, dx, dy, cos_sin=None):
    """Horizontal ray against oriented rectangles (slab test in each box frame); arrays broadcast.
    ``cos_sin``: (cos(yaw), sin(yaw)) when the caller has them already.

    Returns entry and exit distances (entry = exit from inside), the entry face's unit normal in the
    world (pointing back at the camera) and a hit flag.
    """
    cos, sin = (jnp.cos(yaw), jnp.sin(yaw)) if cos_sin is None else cos_sin
    qx, qy = cam[0] - bx, cam[1] - by
    px, py = cos * qx + sin * qy, cos * qy - sin * qx
    lx, ly = cos * dx + sin * dy, cos * dy - sin * dx
    # A ray parallel to a face gets a tiny slope of the same sign: the slab bounds become huge, no NaN.
    lx = jnp.where(lx >= 0, jnp.maximum(lx, 1e-12), jnp.minimum(lx, -1e-12))
    ly = jnp.where(ly >= 0, jnp.maximum(ly, 1e-12), jnp.minimum(ly, -1e-12))
    ix, iy = 1.0 / lx, 1.0 / ly
    ax1, ax2 = (-ex - px) * ix, (ex - px) * ix
    ay1, ay2 = (-ey - py) * iy, (ey - py) * iy
    nx_, fx_ = jnp.minimum(ax1, ax2), jnp.maximum(ax1, ax2)
    ny_, fy_ = jnp.minimum(ay1, ay2), jnp.maximum(ay1, ay2)
    t_in, t_out = jnp.maximum(nx_, ny_), jnp.minimum(fx_, fy_)
    inside = t_in < 0
    # The face is the slab bounding the entry (the exit, from inside); its normal opposes the ray.
    x_face = jnp.where(inside, fx_ < fy_, nx_ > ny_)
    nlx = jnp.where(x_face, -jnp.sign(lx), 0.0)
    nly = jnp.where(x_face, 0.0, -jnp.sign(ly))
    normal = (cos * nlx - sin * nly, sin * nlx + cos * nly)
    return jnp.where(inside, t_out, t_in), t_out, normal, (ex > 0) & (t_in <= t_out) & (t_out >= 0)


def _nearest_ids(scene: Scene, cam, dx, dy, k: int) -> jax.Array:
    """i32[K, W]: the ``k`` primitives (circles then boxes) with the nearest entry along each column.

    Entry distances are computed for all N primitives at once ([N, W]), then K passes each take the
    nearest remaining one per column: the minimum over the major axis, then the lowest row holding it
    (what argmin returns: ties go to the lower index, and columns with fewer than K hits get the first
    misses).  Two plain min reductions, because XLA on CPU runs a (value, index) argmin reduction as a
    scalar loop: the K argmins were a third of a city frame.  Also cheaper than ``lax.top_k`` over a
    small minor axis, than an insertion scan over the N rows and than an unrolled compare/select chain
    over the rows (which XLA re-runs inside every later pass).
    """
    c, b = scene.circles, scene.boxes
    ci, _, _, _, chit = _circle_hits(c[:, :1], c[:, 1:2], c[:, 2:3], cam, dx, dy)
    bi, _, _, bhit = _box_hits(b[:, :1], b[:, 1:2], b[:, 2:3], b[:, 3:4], b[:, 4:5], cam, dx, dy)
    entry = jnp.concatenate([jnp.where(chit, ci, _BIG), jnp.where(bhit, bi, _BIG)], 0)  # [N, W]
    n = entry.shape[0]
    rows = jnp.arange(n, dtype=jnp.int32)[:, None]
    ids = []
    for _ in range(k):
        nearest = jnp.min(entry, axis=0)
        i = jnp.min(jnp.where(entry == nearest, rows, n), axis=0)
        ids.append(i)
        entry = jnp.where(rows == i, 2 * _BIG, entry)
    return jnp.stack(ids)


def _column_data(scene: Scene, cam, dx, dy, ids, cfg: CameraConfig, weights: np.ndarray) -> dict:
    """Column-level hit data of the primitives ``ids`` (i32[W], one per column); entries f32[W].

    Besides distances this precomputes what is constant along a column: the wall's Lambert term (its
    normal is horizontal and fixed per column) and the affine pieces of the dome's Lambert term.
    """
    nc, nb = scene.circles.shape[0], scene.boxes.shape[0]
    table = jnp.concatenate([
        jnp.stack([scene.circles[:, 0], scene.circles[:, 1], scene.circles[:, 2], jnp.zeros_like(scene.circles[:, 0]),
                   jnp.zeros_like(scene.circles[:, 0]), scene.circles[:, 3]], 0),
        jnp.stack([scene.boxes[:, 0], scene.boxes[:, 1], scene.boxes[:, 2], scene.boxes[:, 3], scene.boxes[:, 4],
                   scene.boxes[:, 5]], 0)], 1)  # [6, N]
    x, y, a, bb, yaw, hgt = (jnp.take(table[i], ids, mode="clip") for i in range(6))
    cls = jnp.take(jnp.concatenate([scene.circle_class, scene.box_class]).astype(jnp.int32), ids, mode="clip")
    colors = jnp.concatenate([scene.circle_color, scene.box_color], 0)
    lx, ly, lz = _light(cfg)
    out = dict(height=hgt, cls=cls, color=jnp.stack([jnp.take(col, ids, mode="clip") for col in (colors @ weights.T).T]))  # [C, W]
    # A scene without circles (or without boxes) skips the other kind's math: the counts are static.
    if nc:
        ct_in, ct_out, tc, half, chit = _circle_hits(x, y, a, cam, dx, dy)
        # Circle normal at the entry point, turned toward the camera (it faces away only from inside).
        inv_r = 1.0 / jnp.maximum(a, 1e-6)
        cnx, cny = (cam[0] + ct_in * dx - x) * inv_r, (cam[1] + ct_in * dy - y) * inv_r
        flip = jnp.where(cnx * dx + cny * dy > 0, -1.0, 1.0)
        cnx, cny = flip * cnx, flip * cny
        # dome Lambert = (t * (dx lx + dy ly + s lz) + dome_c) / r, t the horizontal hit distance
        out.update(tc=tc, inv_r=inv_r, dome_c=((cam[0] - x) * lx + (cam[1] - y) * ly + (cam[2] - hgt) * lz) * inv_r)
    if nb:
        # cos / sin of the box yaws over the N primitives, then gathered: the same floats as taking
        # them per column, without K x W trigonometric calls in every field's loop.
        cos_sin = tuple(jnp.take(f(table[4]), ids, mode="clip") for f in (jnp.cos, jnp.sin))
        bt_in, bt_out, (bnx, bny), bhit = _box_hits(x, y, a, bb, yaw, cam, dx, dy, cos_sin)
    if nc and nb:
        circ = ids < nc
        out.update(circ=circ, valid=jnp.where(circ, chit, bhit), t_in=jnp.where(circ, ct_in, bt_in),
                   t_out=jnp.where(circ, ct_out, bt_out), half=jnp.where(circ, half, 0.0))
        nx, ny = jnp.where(circ, cnx, bnx), jnp.where(circ, cny, bny)
    elif nc:
        out.update(valid=chit, t_in=ct_in, t_out=ct_out, half=half)
        nx, ny = cnx, cny
    else:
        out.update(valid=bhit, t_in=bt_in, t_out=bt_out)
        nx, ny = bnx, bny
    out["wall_light"] = jnp.maximum(nx * lx + ny * ly, 0.0)
    return out


def _light(cfg: CameraConfig) -> tuple[float, float, float]:
    light = np.asarray(cfg.light_dir, np.float64)
    return tuple(float(v) for v in light / np.linalg.norm(light))


def _checker(x, y, z, cfg: CameraConfig):
    """+-1 checker of cell ``texture_cell`` in world coordinates (odd offsets keep faces off cell edges)."""
    inv = 1.0 / cfg.texture_cell
    k = jnp.floor(x * inv + 0.237) + jnp.floor(y * inv + 0.419) + jnp.floor(z * inv + 0.613)
    return 1.0 - 2.0 * (k - 2.0 * jnp.floor(0.5 * k))


def render(scene: Scene, pose: jax.Array, cfg: CameraConfig = FOREST_CAMERA):
    """Render one view: ``(image u8[h, w, c], semantic u8[h, w], depth f32[h, w])``.

    ``pose`` is the car's (x, y, yaw) (yaw 0 faces +x, counter-clockwise); ``c`` is 1 for grayscale
    configs else 3.  jit with ``cfg`` closed over or static; vmap over poses (and scenes) for robots.
    Per pixel everything is elementwise over [H, W] (no loop over all primitives; the only gathers
    are the ground paint's class and colour look-ups when a scene has many patches).
    """
    h, w = cfg.height, cfg.width
    along, across, rise = _image_coords(cfg)
    pose = jnp.asarray(pose, jnp.float32)
    cam = camera_origin(pose, cfg)
    z0 = float(cfg.mount_height)
    cos, sin = jnp.cos(pose[2]), jnp.sin(pose[2])
    norm = np.sqrt(along * along + across * across)
    if cfg.projection == "pinhole":  # along = 1: the float order the stored datasets were rendered with
        dx, dy = (cos + sin * across) / norm, (sin - cos * across) / norm  # [W] unit column directions
    else:
        dx, dy = (cos * along + sin * across) / norm, (sin * along - cos * across) / norm
    # Per-pixel constants of the camera (numpy: folded into the compiled code).
    s = (rise[:, None] / norm[None, :]).astype(np.float32)  # [H, W] dz per horizontal metre
    stretch = np.sqrt(1 + s * s).astype(np.float32)  # ray length per horizontal metre
    inv_a = (1 / (1 + s * s)).astype(np.float32)
    inv_down = np.where(s < 0, 1.0 / np.where(s < 0, s, -1.0), 0.0).astype(np.float32)
    inv_up = np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0), 0.0).astype(np.float32)
    lx, ly, lz = _light(cfg)

    # ---- ground and ceiling planes first (the camera height and pixel slopes are constants): they
    # seed the search below as surface codes GROUND / CEIL, obstacles then replace them where nearer.
    t_ground = np.where(s < 0, -z0 * inv_down, _BIG).astype(np.float32)
    ceil = jnp.asarray(scene.ceiling_height, jnp.float32)
    t_ceil = jnp.where((s > 0) & jnp.isfinite(ceil), (ceil - z0) * inv_up, _BIG)
    t = jnp.minimum(t_ground, t_ceil)
    surface = jnp.where(t_ground <= t_ceil, _GROUND, _CEIL)

    # ---- obstacles: the K nearest per column, tested exactly against every pixel.
    weights = _channel_weights(cfg)  # [C, 3]: colours projected onto the output channels once
    k_hits = min(cfg.max_hits, scene.circles.shape[0] + scene.boxes.shape[0])
    if k_hits:
        ids = _nearest_ids(scene, cam, dx, dy, k_hits)  # [K, W]

        def column(_, ids_k):
            """Column data of the k-th nearest primitive of every column."""
            c = _column_data(scene, cam, dx, dy, ids_k, cfg, weights)
            # The camera data ride along, so that per-pixel code reads them from a buffer instead of
            # re-evaluating cos/sin of the pose for every pixel.
            # (Stacked: each scan output is written by a loop of its own, one per step.)
            return None, dict(c, ray=jnp.stack([dx, dy, jnp.broadcast_to(cam[0], dx.shape),
                                                jnp.broadcast_to(cam[1], dx.shape)]))

        _, cand = jax.lax.scan(column, None, ids)  # [K, W] each

        has_circles, has_boxes = scene.circles.shape[0] > 0, scene.boxes.shape[0] > 0

        def candidate(_, c):
            """Hit distance at every pixel of the k-th nearest primitive of each column ([W] values)."""
            hgt = c["height"]
            z_in = z0 + s * c["t_in"]  # ray height at the wall
            wall = c["valid"] & (z_in >= 0) & (z_in <= hgt)
            above = c["valid"] & (z_in > hgt)
            t_other = _BIG
            # (Scenes without circles or without boxes skip the other kind's test: shapes are static.)
            if has_boxes:
                # Box top: seen only from above, i.e. for boxes lower than the camera.
                t_top = (hgt - z0) * inv_down
                top = above & (s < 0) & (t_top <= c["t_out"])
                if has_circles:
                    top = top & ~c["circ"]
                t_other = jnp.where(top, t_top, t_other)
            if has_circles:
                # Dome: in the column's vertical plane a circle of radius ``half`` centred at (tc, height),
                # solved around tc (u = t - tc) so float32 stays accurate far away.
                q = (z0 - hgt) + s * c["tc"]
                disc = c["half"] * c["half"] - q * q * inv_a
                t_dome = c["tc"] - (s * q * inv_a + jnp.sqrt(jnp.maximum(disc, 0.0) * inv_a))
                dome = above & (disc >= 0) & (t_dome >= 0)
                if has_boxes:
                    dome = dome & c["circ"]
                t_other = jnp.where(dome, t_dome, t_other)
            return None, jnp.where(wall, c["t_in"], t_other)

        # Both loops are scans so that what they produce (column data, one distance plane per
        # candidate) are real buffers.  XLA on CPU otherwise fuses producers into every consumer and
        # recomputes them there (the column math and cos/sin of the pose per pixel, the K tests per
        # output channel), which measured 5-10x slower.  (Carrying the nearest distance and surface
        # through the scan instead of K planes measured slower: XLA splits the update into three
        # loops and copies the carry.)
        _, t_k = jax.lax.scan(candidate, None, cand)  # [K, H, W]
        for k in range(k_hits):
            closer = t_k[k] < t
            t, surface = jnp.where(closer, t_k[k], t), jnp.where(closer, k, surface)
        dx, dy, cam_x, cam_y = cand["ray"][0]
    else:
        cam_x, cam_y = cam[0], cam[1]

    # ---- per-pixel surface: distance t and code ``surface`` (candidate k, _GROUND or _CEIL).
    # What follows is written for XLA on CPU, which fuses a producer into *every* consumer and
    # recomputes it there element by element: each output is built from as few shared quantities as
    # possible (the surface code, the patch index, fog and shade), and the RGB channels are packed into
    # one 32-bit word per pixel, because an image stacked along a minor axis of 3 is evaluated byte by
    # byte with all of the shading inside (that alone took 150 of 160 us per forest frame).
    far_h = (cfg.far / stretch).astype(np.float32)  # the far plane as a horizontal distance
    hit = t <= far_h
    is_obj = hit & (surface >= 0)
    is_ground = hit & (surface == _GROUND)
    t = jnp.where(hit, t, 0.0)
    px, py, pz = cam_x + t * dx, cam_y + t * dy, z0 + s * t
    depth = jnp.where(hit, t * stretch, cfg.far)

    # Ground paint (later patches on top): the patch index under each ground pixel, -1 for bare ground
    # (values elsewhere are never used).  At a ground pixel t is exactly the constant t_ground, so the
    # index comes from t_ground (the same floats as px, py there), independent of the obstacles.  With
    # many patches only the rows below the horizon (the only ones that can see the ground) are tested;
    # with a few, every row (the row concatenation then costs more than the tests it saves).
    num_patches = scene.patches.shape[0]
    gather = num_patches > _GATHER_PATCHES
    g0 = int(np.argmax(rise < 0)) if (rise < 0).any() else h  # first row that can see the ground
    g0 = g0 if gather else 0
    patch = jnp.full((h, w), -1, jnp.int32)
    if num_patches and g0 < h:
        t_g = t_ground[g0:]
        gx, gy = cam_x + t_g * dx, cam_y + t_g * dy
        patch_g = jnp.full(gx.shape, -1, jnp.int32)
        for p in range(num_patches):
            x0, y0, x1, y1 = (scene.patches[p, i] for i in range(4))
            # (x test) & (y test): patches with the same x or y range (the city's strips and blocks)
            # share that half when the bounds are compile-time constants (XLA's CSE: a city frame's
            # patch loop went from 109 to 82 ands per pixel).
            patch_g = jnp.where(((gx >= x0) & (gx < x1)) & ((gy >= y0) & (gy < y1)), p, patch_g)
        patch = jnp.concatenate([patch[:g0], patch_g], 0) if g0 else patch_g
    # Many patches (the city's 48): materialise the index once and look class and colour up in a
    # (P+1)-table; select chains would re-run the P tests and P selects inside every output's loop.
    # (Measured on the city: ~1.15x the frame rate of select chains on the same rows.)
    if gather:
        patch = jax.lax.optimization_barrier(patch)

    def by_patch(base, values):  # the patch's value per pixel, ``base`` on bare ground
        if gather:
            table = jnp.concatenate([jnp.asarray(base, values.dtype)[None], values])
            return table.at[patch + 1].get(mode="promise_in_bounds")
        out = base
        for p in range(num_patches):
            out = jnp.where(patch == p, values[p], out)
        return out

    def attr(v):  # the chosen candidate's column value per pixel (a select chain, no gather)
        out = v[0]
        for k in range(1, k_hits):
            out = jnp.where(surface == k, v[k], out)
        return out

    if k_hits:
        # A wall hit is exactly the entry distance; otherwise it is a circle's dome or a box's top.
        if "dome_c" in cand:
            dome_light = jnp.maximum((t * (dx * lx + dy * ly + s * lz) + attr(cand["dome_c"])) * attr(cand["inv_r"]), 0.0)
            other = jnp.where(attr(cand["circ"]), dome_light, lz) if "circ" in cand else dome_light
        else:
            other = lz  # box tops only
        light_obj = jnp.where(t == attr(cand["t_in"]), attr(cand["wall_light"]), other)
        cls_obj = attr(cand["cls"])
    else:
        light_obj, cls_obj = 0.0, 0
    ground_cls = by_patch(scene.ground_class.astype(jnp.int32), scene.patch_class.astype(jnp.int32))
    semantic = jnp.where(is_obj, cls_obj, jnp.where(is_ground, ground_cls, jnp.where(hit, CEILING, SKY)))

    # ---- colour: albedo x (ambient + Lambert) x checker, then fog toward the horizon colour:
    # horizon + fog * (albedo * shade - horizon), where only the albedo differs between channels.
    lambert = jnp.where(is_obj, light_obj, jnp.where(is_ground, max(lz, 0.0), cfg.ceiling_light))
    shade = (cfg.ambient + (1 - cfg.ambient) * lambert) * (1 + cfg.texture_contrast * _checker(px, py, pz, cfg))
    fog = jnp.exp(depth * (-1.0 / cfg.fog_distance))
    fog_shade = fog * shade
    ground_col, patch_col = weights @ scene.ground_color, scene.patch_color @ weights.T  # [C], [P, C]
    ceiling_col = weights @ np.asarray(cfg.ceiling_color, np.float32)
    horizon = weights @ np.asarray(cfg.sky_horizon_color, np.float32)
    zenith = weights @ np.asarray(cfg.sky_zenith_color, np.float32)
    elevation = np.clip(s * 2.0, 0.0, 1.0)
    channels = []
    for i in range(weights.shape[0]):
        obj = attr(cand["color"][:, i]) if k_hits else 0.0
        albedo = jnp.where(is_obj, obj, jnp.where(is_ground, by_patch(ground_col[i], patch_col[:, i]), ceiling_col[i]))
        sky = ((1 - elevation) * horizon[i] + elevation * zenith[i]).astype(np.float32)
        value = jnp.where(hit, horizon[i] + (fog_shade * albedo - fog * horizon[i]), sky)
        channels.append(jnp.clip(value * 255 + 0.5, 0.0, 255.0).astype(jnp.uint8))
    if len(channels) == 1:
        image = channels[0][..., None]
    else:
        # Byte i of the word is channel i in memory order (the bitcast reinterprets the host's bytes).
        shifts = [8 * i if sys.byteorder == "little" else 8 * (3 - i) for i in range(len(channels))]
        packed = sum(ch.astype(jnp.uint32) << shift for ch, shift in zip(channels, shifts))
        image = jax.lax.bitcast_convert_type(packed, jnp.uint8)[..., : len(channels)]
    return image, semantic.astype(jnp.uint8), depth.astype(jnp.float32)


def _channel_weights(cfg: CameraConfig) -> np.ndarray:
    """f32[C, 3]: each output channel as a weighting of RGB (grayscale: the paper's weights, section
    8.2).  Shading is linear in the colours, so a grayscale image is rendered as one channel."""
    if cfg.grayscale:
        return np.asarray([[0.299, 0.587, 0.114]], np.float32)
    return np.eye(3, dtype=np.float32)


def mjx_ray_depth(mjx_model, mjx_data, pose: jax.Array, cfg: CameraConfig = FOREST_CAMERA, *,
                  geomgroup=SCENE_GEOMGROUP, bodyexclude=-1) -> jax.Array:
    """Reference depth f32[h, w]: ``mjx.ray`` along every pixel ray of ``pixel_rays(pose, cfg)``.

    Only geoms in ``geomgroup`` count (default: the scene's geoms, so the car's own body is not seen;
    ``bodyexclude`` is passed through as well).  Same conventions as ``render``: no hit or farther than
    ``cfg.far`` gives ``cfg.far``.  ``mjx_data`` must hold current geom poses (after mjx.kinematics).
    About 100x+ slower than ``render``: for tests and benchmarks only.
    """
    from mujoco import mjx

    origin, dirs = pixel_rays(pose, cfg)

    def one(vec):
        dist, _ = mjx.ray(mjx_model, mjx_data, origin, vec, geomgroup=geomgroup, bodyexclude=bodyexclude)
        return dist

    dist = jax.vmap(one)(dirs.reshape(-1, 3)).reshape(cfg.height, cfg.width)
    return jnp.where((dist < 0) | (dist > cfg.far), cfg.far, dist).astype(jnp.float32)
