"""An exact, fast camera for flat worlds with vertical obstacles (pure JAX, jittable, vmappable).

Why not ``mjx.ray`` per pixel: it tests every pixel against every geom in 3-D.  Our worlds are flat and
every obstacle is vertical (envs/scene.py), so the expensive part factors: with a camera whose image
plane is vertical, all pixels of one image column lie in one *vertical* half-plane, i.e. they share a
single horizontal ray.  We therefore

1. cast one 2-D ray per column against every circle (analytic ray-circle) and every oriented box (slab
   test in the box frame) -> entry/exit distances, a [W, N] problem;
2. keep the K nearest primitives of each column (``CameraConfig.max_hits``);
3. per pixel, intersect the pixel's ray (known slope dz/dt over horizontal distance t) with those K
   candidates in the column's vertical plane -- wall face (z within [0, h] at the entry distance), the
   capsule's top dome, a box top -- and with the ground / ceiling planes, and keep the nearest.

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

import jax
import jax.numpy as jnp
import numpy as np

from envs.scene import CEILING, SCENE_GEOMGROUP, SKY, Scene

_BIG = 1e30  # "no hit" distance inside the computation (finite, so products never make NaN)


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Static camera description (hashable: one compiled renderer per config).

    Geometry: the camera sits ``mount_forward`` m ahead of the car centre at ``mount_height`` m and
    looks ``pitch_deg`` below the horizon (default: at the ground 6 m ahead of the car centre, the
    paper's forest camera, about 3.9 degrees).  Square pixels: the vertical field of view follows from
    ``hfov_deg`` and the aspect ratio.
    """

    width: int = 64
    height: int = 36
    hfov_deg: float = 120.0
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
        if not 0 < self.hfov_deg < 180:
            raise ValueError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")
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


def _image_coords(cfg: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image-plane coordinates: x_j (right) per column and y_i (up) per row, focal length 1."""
    ax = math.tan(math.radians(cfg.hfov_deg) / 2)
    ay = ax * cfg.height / cfg.width
    x = ax * (2 * (np.arange(cfg.width) + 0.5) / cfg.width - 1)
    y = ay * (1 - 2 * (np.arange(cfg.height) + 0.5) / cfg.height) - math.tan(math.radians(cfg.pitch_deg))
    return x.astype(np.float32), y.astype(np.float32)


def camera_origin(pose: jax.Array, cfg: CameraConfig) -> jax.Array:
    """World position f32[3] of the camera for a car pose (x, y, yaw)."""
    pose = jnp.asarray(pose, jnp.float32)
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    return jnp.stack([pose[0] + cfg.mount_forward * c, pose[1] + cfg.mount_forward * s,
                      jnp.asarray(cfg.mount_height, jnp.float32)])


def pixel_rays(pose: jax.Array, cfg: CameraConfig) -> tuple[jax.Array, jax.Array]:
    """The camera model: origin f32[3] and unit world direction f32[h, w, 3] of every pixel."""
    x, y = _image_coords(cfg)
    yaw = jnp.asarray(pose, jnp.float32)[2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    # Car frame: forward (1), left (-x), up (y); rotated by yaw into the world.
    fx, fy = jnp.broadcast_to(1.0, x.shape), -x
    wx, wy = c * fx - s * fy, s * fx + c * fy
    d = jnp.stack([jnp.broadcast_to(wx, (cfg.height, cfg.width)), jnp.broadcast_to(wy, (cfg.height, cfg.width)),
                   jnp.broadcast_to(y[:, None], (cfg.height, cfg.width))], -1)
    return camera_origin(pose, cfg), d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def _column_hits(scene: Scene, cam: jax.Array, dirs: jax.Array):
    """2-D entry/exit distances of every column ray (dirs f32[W, 2], unit) against every primitive.

    Returns per [W, N] (N = circles then boxes): entry distance (_BIG when missed), exit distance,
    horizontal unit normal at the entry facing the camera, and for circles the along-ray distance of
    the centre ``tc`` and the chord half-length ``half`` (which describe the dome's slice).
    """
    # Circles: centre projected on the ray at tc, squared distance of the line from the centre p2.
    cx, cy, r = scene.circles[:, 0], scene.circles[:, 1], scene.circles[:, 2]
    rx, ry = cx - cam[0], cy - cam[1]
    tc = dirs[:, :1] * rx + dirs[:, 1:] * ry  # [W, Nc]
    p2 = rx * rx + ry * ry - tc * tc
    chord2 = r * r - p2
    half = jnp.sqrt(jnp.maximum(chord2, 0.0))
    c_out = tc + half
    # From inside a circle (car pushed into a tree) mjx.ray sees the far wall: enter at the exit.
    c_in = jnp.where(tc - half >= 0, tc - half, c_out)
    c_hit = (r > 0) & (chord2 > 0) & (c_out >= 0)
    c_in, c_out = jnp.where(c_hit, c_in, _BIG), jnp.where(c_hit, c_out, _BIG)
    hx_ = cam[0] + c_in * dirs[:, :1] - cx
    hy_ = cam[1] + c_in * dirs[:, 1:] - cy
    c_norm = jnp.stack([hx_, hy_], -1) / jnp.maximum(r, 1e-6)[:, None]

    # Boxes: slab test in each box frame (rotate the camera and the ray by -yaw).
    bx, by, ex, ey, yaw = (scene.boxes[:, i] for i in range(5))
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    qx, qy = cam[0] - bx, cam[1] - by
    px, py = cos * qx + sin * qy, -sin * qx + cos * qy  # [Nb]
    dx = dirs[:, :1] * cos + dirs[:, 1:] * sin  # [W, Nb]
    dy = -dirs[:, :1] * sin + dirs[:, 1:] * cos
    # A ray parallel to a face gets a tiny slope of the same sign: the slab bounds become huge, no NaN.
    dx = jnp.where(dx >= 0, jnp.maximum(dx, 1e-12), jnp.minimum(dx, -1e-12))
    dy = jnp.where(dy >= 0, jnp.maximum(dy, 1e-12), jnp.minimum(dy, -1e-12))
    ax1, ax2 = (-ex - px) / dx, (ex - px) / dx
    ay1, ay2 = (-ey - py) / dy, (ey - py) / dy
    t_in = jnp.maximum(jnp.minimum(ax1, ax2), jnp.minimum(ay1, ay2))
    b_out = jnp.minimum(jnp.maximum(ax1, ax2), jnp.maximum(ay1, ay2))
    b_hit = (ex > 0) & (t_in <= b_out) & (b_out >= 0)
    inside = t_in < 0
    b_in = jnp.where(inside, b_out, t_in)
    # The face hit is the slab that bounds the entry (or the exit, seen from inside); its normal points
    # back against the ray along that axis.
    x_face = jnp.where(inside, jnp.maximum(ax1, ax2) < jnp.maximum(ay1, ay2),
                       jnp.minimum(ax1, ax2) > jnp.minimum(ay1, ay2))
    nlx = jnp.where(x_face, -jnp.sign(dx), 0.0)
    nly = jnp.where(x_face, 0.0, -jnp.sign(dy))
    b_norm = jnp.stack([cos * nlx - sin * nly, sin * nlx + cos * nly], -1)
    b_in, b_out = jnp.where(b_hit, b_in, _BIG), jnp.where(b_hit, b_out, _BIG)

    nb = scene.boxes.shape[0]
    normal = jnp.concatenate([c_norm, b_norm], 1)
    # Circle normals face outward; seen from inside the circle, flip them toward the camera.
    facing = jnp.sum(normal * dirs[:, None, :], -1) > 0
    normal = jnp.where(facing[..., None], -normal, normal)
    zeros = jnp.zeros((dirs.shape[0], nb), jnp.float32)
    return (jnp.concatenate([c_in, b_in], 1), jnp.concatenate([c_out, b_out], 1), normal,
            jnp.concatenate([tc, zeros], 1), jnp.concatenate([half, zeros], 1))


def _checker(x, y, z, cfg: CameraConfig):
    """+-1 checker of cell ``texture_cell`` in world coordinates (odd offsets keep faces off cell edges)."""
    inv = 1.0 / cfg.texture_cell
    k = jnp.floor(x * inv + 0.237) + jnp.floor(y * inv + 0.419) + jnp.floor(z * inv + 0.613)
    return 1.0 - 2.0 * jnp.mod(k, 2.0)


def render(scene: Scene, pose: jax.Array, cfg: CameraConfig = FOREST_CAMERA):
    """Render one view: ``(image u8[h, w, c], semantic u8[h, w], depth f32[h, w])``.

    ``pose`` is the car's (x, y, yaw) (yaw 0 faces +x, counter-clockwise); ``c`` is 1 for grayscale
    configs else 3.  jit with ``cfg`` closed over or static; vmap over poses (and scenes) for robots.
    """
    h, w = cfg.height, cfg.width
    x_img, y_img = _image_coords(cfg)
    pose = jnp.asarray(pose, jnp.float32)
    cam = camera_origin(pose, cfg)
    z0 = cam[2]
    cos, sin = jnp.cos(pose[2]), jnp.sin(pose[2])
    norm = np.sqrt(1 + x_img * x_img)
    dirs = jnp.stack([(cos + sin * x_img) / norm, (sin - cos * x_img) / norm], -1)  # [W, 2] unit
    slope = jnp.asarray(y_img[:, None] / norm[None, :])  # [H, W] dz per horizontal metre
    stretch = jnp.sqrt(1 + slope * slope)  # ray length per horizontal metre

    # ---- obstacles: K nearest per column, then exact per-pixel tests against those K.
    heights = jnp.concatenate([scene.circles[:, 3], scene.boxes[:, 5]])
    classes = jnp.concatenate([scene.circle_class, scene.box_class]).astype(jnp.int32)
    colors = jnp.concatenate([scene.circle_color, scene.box_color]).astype(jnp.float32)
    radius = jnp.concatenate([scene.circles[:, 2], jnp.zeros_like(scene.boxes[:, 0])])
    is_circle = np.arange(heights.shape[0]) < scene.circles.shape[0]
    n_prim = heights.shape[0]
    s = slope[:, :, None]  # [H, W, 1]
    if n_prim:
        t_in, t_out, normal, tc, half = _column_hits(scene, cam, dirs)
        k = min(cfg.max_hits, n_prim)
        _, idx = jax.lax.top_k(-t_in, k)  # [W, K] nearest entries first

        def pick(a):
            return jnp.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - 2)), axis=1)

        t_in, t_out, normal, tc, half = pick(t_in), pick(t_out), pick(normal), pick(tc), pick(half)
        hgt, circ, rad = heights[idx], jnp.asarray(is_circle)[idx], radius[idx]
        z_in = z0 + s * t_in  # [H, W, K] ray height at the wall
        missed = t_in >= _BIG
        wall = ~missed & (z_in >= 0) & (z_in <= hgt)
        above = ~missed & (z_in > hgt)
        # Dome (capsule top cap) in the column's vertical plane: a circle of radius ``half`` centred at
        # (tc, hgt).  Solved around tc (u = t - tc) to keep float32 accurate far away.
        q = z0 + s * tc - hgt
        a = 1 + s * s
        disc = a * half * half - q * q
        u1 = (-s * q - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
        t_dome = tc + u1
        dome = circ & above & (disc >= 0) & (t_dome >= 0)
        # Box top (only visible from above, i.e. for boxes lower than the camera).
        t_top = (hgt - z0) / jnp.where(s < 0, s, -1.0)
        top = ~circ & above & (s < 0) & (t_top <= t_out)
        t_k = jnp.where(wall, t_in, jnp.where(dome, t_dome, jnp.where(top, t_top, _BIG)))
        best = jnp.argmin(t_k, axis=-1)[..., None]  # [H, W, 1]
        t_obj = jnp.take_along_axis(t_k, best, -1)[..., 0]
        kind = jnp.take_along_axis(jnp.where(wall, 0, jnp.where(dome, 1, 2)), best, -1)[..., 0]
        prim = jnp.take_along_axis(jnp.broadcast_to(idx, t_k.shape), best, -1)[..., 0]  # [H, W]
        col_pick = jnp.broadcast_to(jnp.arange(w)[None, :], (h, w))
        wall_n = normal[col_pick, best[..., 0]]  # [H, W, 2]
        obj_h = heights[prim]
        obj_r = jnp.maximum(radius[prim], 1e-6)
    else:
        t_obj = jnp.full((h, w), _BIG, jnp.float32)
        kind = prim = jnp.zeros((h, w), jnp.int32)
        wall_n = jnp.zeros((h, w, 2), jnp.float32)
        obj_h = jnp.zeros((h, w), jnp.float32)
        obj_r = jnp.ones((h, w), jnp.float32)

    # ---- ground and ceiling planes.
    t_ground = jnp.where(slope < 0, -z0 / jnp.where(slope < 0, slope, -1.0), _BIG)
    ceil = jnp.asarray(scene.ceiling_height, jnp.float32)
    t_ceil = jnp.where((slope > 0) & jnp.isfinite(ceil), (ceil - z0) / jnp.where(slope > 0, slope, 1.0), _BIG)
    t = jnp.minimum(t_obj, jnp.minimum(t_ground, t_ceil))
    depth = t * stretch
    hit = depth <= cfg.far
    is_obj = hit & (t_obj <= jnp.minimum(t_ground, t_ceil))
    is_ground = hit & ~is_obj & (t_ground <= t_ceil)
    is_ceil = hit & ~is_obj & ~is_ground
    t = jnp.where(hit, t, 0.0)
    px = cam[0] + t * dirs[None, :, 0]
    py = cam[1] + t * dirs[None, :, 1]
    pz = z0 + slope * t

    # ---- ground paint: the last patch containing the point wins (later patches are drawn on top).
    pr = scene.patches
    inside = ((px[..., None] >= pr[:, 0]) & (px[..., None] < pr[:, 2])
              & (py[..., None] >= pr[:, 1]) & (py[..., None] < pr[:, 3]))  # [H, W, Np]
    top_patch = jnp.max(jnp.where(inside, jnp.arange(pr.shape[0]), -1), axis=-1, initial=-1)
    painted = top_patch >= 0
    safe_patch = jnp.maximum(top_patch, 0)
    ground_cls = jnp.where(painted, scene.patch_class[safe_patch] if pr.shape[0] else 0, scene.ground_class)
    ground_col = (jnp.where(painted[..., None], scene.patch_color[safe_patch], scene.ground_color)
                  if pr.shape[0] else jnp.broadcast_to(scene.ground_color, (h, w, 3)))

    # ---- semantic class.
    obj_cls = classes[prim] if n_prim else jnp.zeros((h, w), jnp.int32)
    semantic = jnp.where(is_obj, obj_cls, jnp.where(is_ground, ground_cls, jnp.where(is_ceil, CEILING, SKY)))

    # ---- colour: albedo x (ambient + Lambert) x checker, then fog toward the horizon colour.
    if scene.circles.shape[0]:
        # Dome normal: from the sphere centre (circle centre at the cylinder's top) to the hit point.
        circle = scene.circles[jnp.minimum(prim, scene.circles.shape[0] - 1)]
        dome_n = jnp.stack([px - circle[..., 0], py - circle[..., 1], pz - obj_h], -1) / obj_r[..., None]
    else:
        dome_n = jnp.zeros((h, w, 3), jnp.float32)
    wall_n3 = jnp.concatenate([wall_n, jnp.zeros((h, w, 1), jnp.float32)], -1)
    obj_n = jnp.where((kind == 0)[..., None], wall_n3, jnp.where((kind == 1)[..., None], dome_n, jnp.asarray([0.0, 0.0, 1.0])))
    light = np.asarray(cfg.light_dir, np.float32)
    light = light / np.linalg.norm(light)
    lambert = jnp.where(is_obj, jnp.maximum(jnp.sum(obj_n * light, -1), 0.0),
                        jnp.where(is_ground, max(float(light[2]), 0.0), cfg.ceiling_light))
    albedo = jnp.where(is_obj[..., None], colors[prim] if n_prim else 0.0,
                       jnp.where(is_ground[..., None], ground_col, jnp.asarray(cfg.ceiling_color, jnp.float32)))
    shade = (cfg.ambient + (1 - cfg.ambient) * lambert) * (1 + cfg.texture_contrast * _checker(px, py, pz, cfg))
    color = albedo * shade[..., None]
    fog = jnp.exp(-depth / cfg.fog_distance)[..., None]
    horizon = jnp.asarray(cfg.sky_horizon_color, jnp.float32)
    color = fog * color + (1 - fog) * horizon
    elevation = jnp.clip(slope * 2.0, 0.0, 1.0)[..., None]
    sky = (1 - elevation) * horizon + elevation * jnp.asarray(cfg.sky_zenith_color, jnp.float32)
    color = jnp.where(hit[..., None], color, sky)

    if cfg.grayscale:
        color = jnp.sum(color * jnp.asarray([0.299, 0.587, 0.114], jnp.float32), -1, keepdims=True)
    image = jnp.round(jnp.clip(color, 0.0, 1.0) * 255).astype(jnp.uint8)
    depth = jnp.where(hit, depth, cfg.far).astype(jnp.float32)
    return image, semantic.astype(jnp.uint8), depth


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
