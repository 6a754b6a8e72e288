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
