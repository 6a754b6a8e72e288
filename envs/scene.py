"""Scene geometry as arrays: the single source of truth for the MJCF, the collisions and the camera.

Every world is flat with vertical obstacles, so a scene is fully described by
* vertical circles (trees, rocks, pillars): MuJoCo capsules standing on the ground,
* vertical oriented boxes (walls, buildings, doors, parked cars),
* ground paint: axis-aligned rectangles of a semantic class and colour drawn over a base ground
  (roads, lane markings, sidewalks), later rectangles on top,
* an optional ceiling (indoor halls), else open sky.

Each scene family has a fixed count of every kind (``Scene.circles.shape[0]`` etc.); procedural variety
changes only values, so one compiled step and renderer serve every layout.  Unused slots are disabled
by a zero radius / zero half-extent and are ignored by the camera and placed far below the ground in
the MJCF.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# Semantic classes of the camera's class map (u8).  One table for every scene so labellers and metrics
# agree on the ids.
SKY, GRASS, ROAD, LANE_LINE, EDGE_LINE, SIDEWALK, TREE, ROCK, WALL, BUILDING, CAR, DOOR, FLOOR, CEILING = range(14)
CLASS_NAMES = (
    "sky", "grass", "road", "lane_line", "edge_line", "sidewalk", "tree", "rock",
    "wall", "building", "car", "door", "floor", "ceiling",
)
NUM_CLASSES = len(CLASS_NAMES)


@struct.dataclass
class Scene:
    """Arrays describing one layout (all float32 unless noted)."""

    circles: jax.Array  # [Nc, 4] x, y, radius, height   (radius 0 = unused slot)
    circle_class: jax.Array  # i32[Nc]
    circle_color: jax.Array  # [Nc, 3] in [0, 1]
    boxes: jax.Array  # [Nb, 6] cx, cy, half_x, half_y, yaw, height   (half_x == 0 = unused slot)
    box_class: jax.Array  # i32[Nb]
    box_color: jax.Array  # [Nb, 3]
    patches: jax.Array  # [Np, 4] xmin, ymin, xmax, ymax of ground paint
    patch_class: jax.Array  # i32[Np]
    patch_color: jax.Array  # [Np, 3]
    ground_class: jax.Array  # i32[]   class of unpainted ground
    ground_color: jax.Array  # [3]
    ceiling_height: jax.Array  # f32[]   +inf for open sky
    bounds: jax.Array  # [4] xmin, ymin, xmax, ymax of the drivable world (for plots and sampling)


def empty_scene(num_circles: int, num_boxes: int, num_patches: int) -> Scene:
    """A scene with every slot unused; builders fill slots with ``.at[i].set``."""
    return Scene(
        circles=jnp.zeros((num_circles, 4), jnp.float32),
        circle_class=jnp.full((num_circles,), TREE, jnp.int32),
        circle_color=jnp.zeros((num_circles, 3), jnp.float32),
        boxes=jnp.zeros((num_boxes, 6), jnp.float32),
        box_class=jnp.full((num_boxes,), WALL, jnp.int32),
        box_color=jnp.zeros((num_boxes, 3), jnp.float32),
        patches=jnp.zeros((num_patches, 4), jnp.float32),
        patch_class=jnp.full((num_patches,), ROAD, jnp.int32),
        patch_color=jnp.zeros((num_patches, 3), jnp.float32),
        ground_class=jnp.asarray(GRASS, jnp.int32),
        ground_color=jnp.asarray([0.35, 0.45, 0.25], jnp.float32),
        ceiling_height=jnp.asarray(np.inf, jnp.float32),
        bounds=jnp.asarray([-1.0, -1.0, 1.0, 1.0], jnp.float32),
    )


# ------------------------------------------------------------------------------------------------ MJCF
#
# How a Scene becomes MuJoCo geoms (the camera in envs/camera.py draws exactly these shapes):
#
# * circle (x, y, r, h) -> a vertical capsule of radius r whose *cylindrical part* spans z in [0, h]
#   (centre z = h/2, half-length h/2).  Its bottom hemisphere lies below the ground plane, where no ray
#   from above reaches and nothing collides; its top hemisphere is a dome from z = h to z = h + r, and
#   the camera draws that dome too, so camera depth and mjx.ray agree everywhere.  Why the cylinder and
#   not the dome is anchored at h: the car chassis lives at z in [0, 0.5] and every circle's cylinder
#   reaches the ground, so the collision footprint is the full circle of radius r for any h >= 0, just
#   like the camera's wall.  (MJX has no cylinder-vs-box collision, hence capsules.)  A scene that wants
#   a rock whose overall top is T uses h = max(T - r, 0).
# * box (cx, cy, hx, hy, yaw, h) -> a box geom centred at (cx, cy, h/2) with half-sizes (hx, hy, h/2),
#   rotated by yaw about +z: it spans z in [0, h] exactly.
# * ground -> an infinite plane at z = 0; ceiling (finite ceiling_height only) -> a downward-facing
#   plane.  Neither collides (the car is planar and never touches them).
# * Obstacles use contype=1 conaffinity=2: they never collide with one another (no wasted contact
#   pairs), only with a body of contype=2 / conaffinity=1 (the car chassis).
# * Every scene geom is in geom group SCENE_GEOM_GROUP, so ``mjx.ray`` with SCENE_GEOMGROUP sees the
#   world and not the car (car geoms must use another group; MuJoCo's default group 0 is fine).
#
# Geom ordering with keep_unused=True (what update_model_geometry relies on): the scene's geoms are the
# first geoms of <worldbody>, before ``car_xml``:
#     0                      ground plane
#     1 .. Nc                circle slots in order (circle i -> geom 1 + i)
#     1+Nc .. Nc+Nb          box slots in order (box j -> geom 1 + Nc + j)
#     1+Nc+Nb                ceiling plane, present only when ceiling_height is finite
# and the car's geoms follow.  Unused slots are parked at z = PARK_Z with size PARK_SIZE, so every
# layout of a scene family (same slot counts, same ceiling or not) compiles to the same geom count and
# the same contact pairs, and a new layout is just new geom_pos/size/quat values.

SCENE_GEOM_GROUP = 1
SCENE_GEOMGROUP = tuple(int(g == SCENE_GEOM_GROUP) for g in range(6))  # the mask mjx.ray takes
OBSTACLE_CONTYPE, OBSTACLE_CONAFFINITY = 1, 2
PARK_Z = -100.0
PARK_SIZE = 1e-3
_MIN_HALF = 1e-4  # MuJoCo rejects zero sizes; a zero-height circle becomes a sphere-like stub


def scene_geom_arrays(scene: Scene) -> dict:
    """MuJoCo pos/size/quat/rgba of every circle and box slot (jnp, jittable, works on a batched scene).

    Returns a dict of arrays with leading slot axes: ``circle_pos [.., Nc, 3]``, ``circle_size [.., Nc, 3]``
    (radius, half-length, 0), ``circle_quat [.., Nc, 4]``, ``circle_rgba``, and the same for ``box_*``.
    Unused slots get the parked placement described above.
    """
    c = jnp.asarray(scene.circles, jnp.float32)
    used = c[..., 2] > 0
    half = jnp.maximum(0.5 * c[..., 3], _MIN_HALF)
    circle_pos = jnp.stack([c[..., 0], c[..., 1], half], -1)
    circle_size = jnp.stack([c[..., 2], half, jnp.zeros_like(half)], -1)
    circle_pos = jnp.where(used[..., None], circle_pos, jnp.asarray([0.0, 0.0, PARK_Z]))
    circle_size = jnp.where(used[..., None], circle_size, jnp.asarray([PARK_SIZE, PARK_SIZE, 0.0]))
    circle_quat = jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0, 0.0]), c.shape[:-1] + (4,))

    b = jnp.asarray(scene.boxes, jnp.float32)
    bused = b[..., 2] > 0
    bhalf = jnp.maximum(0.5 * b[..., 5], _MIN_HALF)
    box_pos = jnp.stack([b[..., 0], b[..., 1], bhalf], -1)
    box_size = jnp.stack([jnp.maximum(b[..., 2], _MIN_HALF), jnp.maximum(b[..., 3], _MIN_HALF), bhalf], -1)
    yaw = b[..., 4]
    zeros = jnp.zeros_like(yaw)
    box_quat = jnp.stack([jnp.cos(0.5 * yaw), zeros, zeros, jnp.sin(0.5 * yaw)], -1)
    box_pos = jnp.where(bused[..., None], box_pos, jnp.asarray([0.0, 0.0, PARK_Z]))
    box_size = jnp.where(bused[..., None], box_size, jnp.full((3,), PARK_SIZE))
    box_quat = jnp.where(bused[..., None], box_quat, jnp.asarray([1.0, 0.0, 0.0, 0.0]))

    ones_c = jnp.ones(c.shape[:-1] + (1,), jnp.float32)
    ones_b = jnp.ones(b.shape[:-1] + (1,), jnp.float32)
    return dict(
        circle_pos=circle_pos, circle_size=circle_size, circle_quat=circle_quat,
        circle_rgba=jnp.concatenate([jnp.asarray(scene.circle_color, jnp.float32), ones_c], -1),
        box_pos=box_pos, box_size=box_size, box_quat=box_quat,
        box_rgba=jnp.concatenate([jnp.asarray(scene.box_color, jnp.float32), ones_b], -1),
        circle_used=used, box_used=bused,
    )


def _fmt(values) -> str:
    # 9 significant digits round-trip float32 exactly, so the MJCF and update_model_geometry agree.
    return " ".join(f"{float(v):.9g}" for v in np.asarray(values, np.float32).reshape(-1))


def scene_to_mjcf(scene: Scene, *, car_xml: str = "", extra_xml: str = "", name: str = "scene",
                  keep_unused: bool = True) -> str:
    """A complete MJCF string for one (unbatched) scene; see the comment block above for the mapping.

    ``car_xml`` is inserted verbatim into <worldbody> after the scene's geoms; ``extra_xml`` verbatim at
    the top level after </worldbody> (actuators, sensors, <option>, ...).  With ``keep_unused=False``
    unused slots are omitted (smaller model, but geom count and ordering then depend on the layout and
    ``update_model_geometry`` does not apply).
    """
    if np.ndim(scene.circles) != 2 or np.ndim(scene.boxes) != 2:
        raise ValueError("scene_to_mjcf takes one scene, not a batch (circles must be [Nc, 4])")
    arrays = jax.tree.map(np.asarray, scene_geom_arrays(scene))
    ground = np.clip(np.asarray(scene.ground_color, np.float32), 0, 1)
    obstacle = f'contype="{OBSTACLE_CONTYPE}" conaffinity="{OBSTACLE_CONAFFINITY}" group="{SCENE_GEOM_GROUP}"'
    lines = [
        f'<mujoco model="{name}">',
        "  <asset>",
        # mjx.ray indexes mat_rgba, which fails on a model without any material: keep at least one.
        f'    <material name="ground" rgba="{_fmt(ground)} 1"/>',
        '    <material name="ceiling" rgba="0.85 0.85 0.82 1"/>',
        "  </asset>",
        "  <worldbody>",
        f'    <geom name="ground" type="plane" size="0 0 1" material="ground" contype="0" conaffinity="0" '
        f'group="{SCENE_GEOM_GROUP}"/>',
    ]
    for kind, shape in (("circle", "capsule"), ("box", "box")):
        for i in range(arrays[f"{kind}_pos"].shape[0]):
            if not (keep_unused or arrays[f"{kind}_used"][i]):
                continue
            lines.append(
                f'    <geom name="{kind}{i}" type="{shape}" pos="{_fmt(arrays[f"{kind}_pos"][i])}" '
                f'size="{_fmt(arrays[f"{kind}_size"][i][:2 if shape == "capsule" else 3])}" '
                f'quat="{_fmt(arrays[f"{kind}_quat"][i])}" rgba="{_fmt(arrays[f"{kind}_rgba"][i])}" {obstacle}/>'
            )
    ceiling = float(np.asarray(scene.ceiling_height))
    if np.isfinite(ceiling):
        # A plane faces its local +z; turned 180 degrees about x it faces down at the ceiling height.
        lines.append(
            f'    <geom name="ceiling" type="plane" size="0 0 1" pos="0 0 {ceiling:.9g}" quat="0 1 0 0" '
            f'material="ceiling" contype="0" conaffinity="0" group="{SCENE_GEOM_GROUP}"/>'
        )
    lines += [car_xml, "  </worldbody>", extra_xml, "</mujoco>"]
    return "\n".join(line for line in lines if line)


def update_model_geometry(mjx_model, scene: Scene):
    """Return ``mjx_model`` with the obstacle geoms moved to ``scene``'s layout (no recompilation).

    ``mjx_model`` must come from ``scene_to_mjcf(s, keep_unused=True)`` of a scene ``s`` of the same
    family (same slot counts); geoms 1 .. Nc+Nb are overwritten in the documented order.  Updates
    geom_pos/size/quat/rgba and the bounding data (geom_rbound, geom_aabb) MJX's broad phase may read.
    Pure jnp: jit it, or vmap it over a batch of scenes with ``in_axes=(None, 0)`` for per-robot
    layouts.  Run ``mjx.kinematics``/``mjx.forward`` afterwards so ``geom_xpos`` follows.
    """
    if np.ndim(scene.circles) != 2:
        raise ValueError("update_model_geometry takes one scene; vmap it for a batch")
    nc, nb = scene.circles.shape[0], scene.boxes.shape[0]
    if mjx_model.ngeom < 1 + nc + nb:
        raise ValueError(f"model has {mjx_model.ngeom} geoms, a scene with {nc} circles and {nb} boxes "
                         f"needs at least {1 + nc + nb} (build it with scene_to_mjcf(keep_unused=True))")
    a = scene_geom_arrays(scene)
    sl = slice(1, 1 + nc + nb)
    pos = jnp.concatenate([a["circle_pos"], a["box_pos"]], -2)
    size = jnp.concatenate([a["circle_size"], a["box_size"]], -2)
    quat = jnp.concatenate([a["circle_quat"], a["box_quat"]], -2)
    rgba = jnp.concatenate([a["circle_rgba"], a["box_rgba"]], -2)
    # Bounding sphere and local AABB exactly as MuJoCo's compiler defines them for capsules and boxes.
    cap_r, cap_h = a["circle_size"][..., 0], a["circle_size"][..., 1]
    rbound = jnp.concatenate([cap_r + cap_h, jnp.linalg.norm(a["box_size"], axis=-1)], -1)
    cap_half = jnp.stack([cap_r, cap_r, cap_r + cap_h], -1)
    aabb = jnp.concatenate([jnp.zeros_like(pos), jnp.concatenate([cap_half, a["box_size"]], -2)], -1)

    def put(field, value):
        return jnp.asarray(field).at[sl].set(value)

    return mjx_model.replace(
        geom_pos=put(mjx_model.geom_pos, pos),
        geom_size=put(mjx_model.geom_size, size),
        geom_quat=put(mjx_model.geom_quat, quat),
        geom_rgba=put(mjx_model.geom_rgba, rgba),
        geom_aabb=put(mjx_model.geom_aabb, aabb),
        geom_rbound=jnp.asarray(mjx_model.geom_rbound).at[sl].set(rbound),
    )
