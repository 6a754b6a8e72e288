"""Indoor halls (the paper's real RC car on a floor of Cory Hall): a corridor loop with doors.

Layout: a rectangular corridor loop whose centreline is ``2 * (2 half_x + 2 half_y)`` = 75 m long by
default, ``corridor_width`` wide, under a ceiling.  Five intersections: dead-end side corridors
(``stub_length`` long) branch off the four corners, each continuing one of the two corridors that
meet there (a pinwheel), and one off the middle of the bottom side.  Walls are boxes: the solid inner
block, thin outer walls with openings for the side corridors, and the side corridors' walls.  Doors are
thin boxes of class DOOR (a distinct wood colour) standing 3 cm proud of random wall faces; their
positions come from the seed, their count is fixed.

Tasks: drive once around the loop from a start point (at least ``start_margin`` from any
intersection) -- counter-clockwise for 'train', clockwise for 'eval' and 'val', with disjoint door seeds.  The
route is a closed polyline; at each intersection a heading command (the world heading of the route's
outgoing corridor: turn at a corner, straight at the middle junction) is issued ``command_lead_s``
seconds (at the fixed speed) before the car reaches it, and stays until the next one.
``info['goal_heading']`` is the current command (the route's direction before the first one).

Signals add ``door_frac`` (the fraction of the image that is door, from the true class map).  Metrics:
``route_fraction`` (fraction of the loop traversed), ``crash``, ``turns`` (intersections passed with the
heading within 45 degrees of the command), ``turns_total`` (intersections passed), ``door_fraction``
(mean door_frac).  Steering only (A = 1, degrees, env box +-45, planning +-30) at a fixed 0.5 m/s, with
the paper's RC-car scale (``RC_CAR``, 0.5 m long) in 3 m hallways.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import base
from envs.camera import HALL_CAMERA, CameraConfig
from envs.car import CarConfig
from envs.scene import DOOR, FLOOR, WALL, Scene, empty_scene
from envs.scenes import common

_NUM_JUNCTIONS = 5


# The paper's halls car is a real 1/10-scale RC car (caps-algorithm.md 9.3), not the 2 m forest/city car:
# 0.5 x 0.3 m, 0.3 m wheelbase (turning radius 0.52 m at the planner's 30 degree steer), 3 kg; the
# cornering stiffness keeps the 10 kg car's stiffness per unit of tyre load.  Its camera sits on a mast
# 0.2 m ahead of the centre at the 0.375 m height of the other scenes' cameras.
RC_CAR = CarConfig(half_length=0.25, half_width=0.15, half_height=0.1, mass=3.0, front_axle=0.15,
                   rear_axle=0.15, cornering_stiffness=150.0, near_circles=0, near_boxes=4, max_speed=1.0)
RC_CAMERA = dataclasses.replace(HALL_CAMERA, mount_forward=0.2)


@dataclasses.dataclass(frozen=True)
class IndoorConfig(common.SceneConfig):
    camera: CameraConfig = RC_CAMERA
    car: CarConfig = RC_CAR
    fixed_speed: float | None = 0.5
    speed_limit: float = 1.0
    half_x: float = 12.5  # half sizes of the loop's centreline rectangle (75 m around by default)
    half_y: float = 6.25
    corridor_width: float = 3.0  # a university hallway: six RC-car lengths
    wall_thickness: float = 0.2
    wall_height: float = 2.7
    ceiling_height: float = 2.7
    stub_length: float = 5.0
    doors: int = 14
    door_width: float = 0.9
    door_height: float = 2.1
    door_proud: float = 0.03  # how far a door stands out of its wall
    command_lead_s: float = 2.0
    start_margin: float = 4.0
    finish_tolerance: float = 0.5

    @property
    def c(self) -> float:
        return self.corridor_width / 2

    def junctions(self) -> np.ndarray:
        """f32[5, 4]: each intersection's centre (x, y) and its side corridor's direction (dx, dy)."""
        a, b = self.half_x, self.half_y
        return np.asarray([
            [a, -b, 1, 0],  # bottom-right corner, the bottom corridor continues east
            [a, b, 0, 1],  # top-right, the right corridor continues north
            [-a, b, -1, 0],
            [-a, -b, 0, -1],
            [0, -b, 0, -1],  # middle of the bottom side, a corridor south
        ], np.float32)

    def walls(self) -> np.ndarray:
        """f32[N, 6] wall boxes (fixed per config): inner block, outer walls with openings, stub walls."""
        a, b, c, t, h = self.half_x, self.half_y, self.c, self.wall_thickness, self.wall_height
        boxes = [[0.0, 0.0, a - c, b - c, 0.0, h]]  # the solid block inside the loop
        j = self.junctions()
        # Outer walls: one line per side, cut where a side corridor leaves through it.
        sides = [  # (axis the wall runs along, its fixed coordinate, outward direction)
            (0, -b - c - t / 2, (0, -1)), (0, b + c + t / 2, (0, 1)),
            (1, a + c + t / 2, (1, 0)), (1, -a - c - t / 2, (-1, 0)),
        ]
        for axis, fixed, out in sides:
            span = (a if axis == 0 else b) + c + t
            cuts = sorted(float(p[axis]) for p in j if (p[2], p[3]) == out)
            lo = -span
            for cut in cuts + [None]:
                hi = span if cut is None else cut - c
                if hi > lo + 1e-6:
                    mid, half = (lo + hi) / 2, (hi - lo) / 2
                    boxes.append([mid, fixed, half, t / 2, 0.0, h] if axis == 0 else [fixed, mid, t / 2, half, 0.0, h])
                lo = span if cut is None else cut + c
        # Side corridors: two side walls and an end wall each.
        for x, y, dx, dy in j:
            start = abs(y) + c if dy else abs(x) + c
            mid = start + self.stub_length / 2
            for side in (-1, 1):
                if dy:
                    boxes.append([x + side * (c + t / 2), dy * mid, t / 2, self.stub_length / 2 + t, 0.0, h])
                else:
                    boxes.append([dx * mid, y + side * (c + t / 2), self.stub_length / 2 + t, t / 2, 0.0, h])
            end = start + self.stub_length + t / 2
            boxes.append([x, dy * end, c + t, t / 2, 0.0, h] if dy else [dx * end, y, t / 2, c + t, 0.0, h])
        return np.asarray(boxes, np.float32)

    def faces(self) -> np.ndarray:
        """f32[F, 5] wall faces that line the loop: x0, y0 (start), dx, dy (unit, along), length.

        The corridor lies to the left of the direction of travel along each face.
        """
        a, b, c = self.half_x, self.half_y, self.c
        out = []
        # Inner block, counter-clockwise seen from the corridor: corridor on the left when walking
        # clockwise around the block, so walk the block's edges clockwise.
        ia, ib = a - c, b - c
        for (x0, y0), (x1, y1) in [((-ia, -ib), (-ia, ib)), ((-ia, ib), (ia, ib)), ((ia, ib), (ia, -ib)), ((ia, -ib), (-ia, -ib))]:
            out.append([x0, y0, x1, y1])
        # Outer walls, walked counter-clockwise (corridor on the left), split at the openings.
        oa, ob = a + c, b + c
        corners = [(-oa, -ob), (oa, -ob), (oa, ob), (-oa, ob), (-oa, -ob)]
        j = self.junctions()
        for (x0, y0), (x1, y1) in zip(corners[:-1], corners[1:]):
            d = np.sign([x1 - x0, y1 - y0])
            axis = 0 if d[0] else 1
            fixed = y0 if axis == 0 else x0
            out_dir = (0, int(np.sign(fixed))) if axis == 0 else (int(np.sign(fixed)), 0)
            cuts = [float(p[axis]) for p in j if (p[2], p[3]) == out_dir]
            lo, hi = (x0, x1) if axis == 0 else (y0, y1)
            pts = sorted([lo, hi] + [q for cut in cuts for q in (cut - c, cut + c)], reverse=bool(d[axis] < 0))
            for p0, p1 in zip(pts[0::2], pts[1::2]):
                out.append([p0, fixed, p1, fixed] if axis == 0 else [fixed, p0, fixed, p1])
        faces = []
        for x0, y0, x1, y1 in out:
            length = float(np.hypot(x1 - x0, y1 - y0))
            if length > 1e-6:
                faces.append([x0, y0, (x1 - x0) / length, (y1 - y0) / length, length])
        return np.asarray(faces, np.float32)


@struct.dataclass
class IndoorTask:
    seed: jax.Array  # u32[2]: raw key data of the door layout
    route: jax.Array  # f32[6, 2]: start, the four corners in driving order, back to the start
    junction_s: jax.Array  # f32[5]: arc length of each intersection along the route (ascending)
    commands: jax.Array  # f32[5]: world heading commanded at each intersection


class IndoorEnv(common.SceneEnv):
    extra_signals = ("door_frac",)

    def __init__(self, config: IndoorConfig = IndoorConfig()):
        super().__init__(config)

    # ---------------------------------------------------------------- tasks

    def sample_task(self, key: jax.Array, split: str = "train") -> IndoorTask:
        cfg = self.config
        key = self.split_key(key, split)
        k_seed, k_start = jax.random.split(key)
        loop, junction_s, commands = self._loop(split == "train")
        perimeter = float(np.sum(np.linalg.norm(np.diff(loop, axis=0), axis=-1)))
        # Start anywhere at least start_margin from every intersection (a fine grid of candidates).
        grid = np.linspace(0.0, perimeter, 512, endpoint=False, dtype=np.float32)
        gap = np.abs((grid[:, None] - junction_s[None, :] + perimeter / 2) % perimeter - perimeter / 2)
        ok = jnp.asarray(np.all(gap >= cfg.start_margin, axis=-1))
        s0 = jnp.asarray(grid)[jax.random.categorical(k_start, jnp.where(ok, 0.0, -jnp.inf))]
        closed = jnp.asarray(loop)
        start, _ = common.path_point(closed, s0)
        # The route: from the start around the loop (its corners in order) back to the start.
        corner_s = jnp.asarray(np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=-1))])[:4])
        order = jnp.argsort((corner_s - s0) % perimeter)
        route = jnp.concatenate([start[None], closed[:4][order], start[None]])
        rel = (jnp.asarray(junction_s) - s0) % perimeter
        idx = jnp.argsort(rel)
        return IndoorTask(seed=jax.random.key_data(k_seed).astype(jnp.uint32), route=route.astype(jnp.float32),
                          junction_s=rel[idx].astype(jnp.float32),
                          commands=jnp.asarray(commands)[idx].astype(jnp.float32))

    def _loop(self, ccw: bool):
        """The closed loop f32[5, 2] in driving order, and the arc length and outgoing heading of each
        intersection along it (numpy: fixed per config and direction)."""
        a, b = self.config.half_x, self.config.half_y
        loop = np.asarray([[-a, -b], [a, -b], [a, b], [-a, b]], np.float32)
        if not ccw:
            loop = loop[::-1]
        loop = np.concatenate([loop, loop[:1]])
        lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=-1))])
        junction_s, commands = [], []
        for p in self.config.junctions()[:, :2]:
            # Every junction lies on the loop: find its edge and offset (the first match, so a corner
            # is at the start of the edge that leaves it).
            for i in range(4):
                d = loop[i + 1] - loop[i]
                t = float(np.dot(p - loop[i], d) / np.dot(d, d))
                if 0 <= t < 1 and np.linalg.norm(loop[i] + t * d - p) < 1e-4:
                    break
            junction_s.append(lengths[i] + t * np.linalg.norm(d))
            commands.append(float(np.arctan2(d[1], d[0])))
        return loop, np.asarray(junction_s, np.float32), np.asarray(commands, np.float32)

    def layout(self, task: IndoorTask) -> Scene:
        return indoor_layout(self.config, task.seed)

    def start_pose(self, task: IndoorTask) -> jax.Array:
        _, heading = common.path_point(task.route, jnp.zeros(()))
        return jnp.concatenate([task.route[0], heading[None]]).astype(jnp.float32)

    # ---------------------------------------------------------------- progress

    def task_init(self, task: IndoorTask, pose):
        zero = jnp.zeros((), jnp.float32)
        s = jnp.zeros((), jnp.float32)
        info = {"route_s": s, "goal_heading": self._command(task, s, pose[2])}
        metrics = {"route_fraction": zero, "crash": zero, "turns": zero, "turns_total": zero,
                   "door_fraction": zero, "steps": zero}
        return info, metrics

    def task_update(self, state, pose, signals):
        cfg, task, m = self.config, state.task, state.metrics
        s_prev = state.info["route_s"]
        s, _ = common.project_on_path(task.route, pose[:2], s_prev - 1.0, s_prev + 2.0)
        s = jnp.maximum(s, s_prev)
        length = common.polyline_lengths(task.route)[-1]
        # An intersection is passed once the car is half a corridor beyond its centre along the route.
        exit_s = task.junction_s + cfg.c
        passed = (s_prev < exit_s) & (s >= exit_s)
        error = jnp.abs(base.wrap_angle(pose[2] - task.commands))
        steps = m["steps"] + 1
        metrics = {
            "route_fraction": s / length,
            "crash": jnp.maximum(m["crash"], signals["collision"]),
            "turns": m["turns"] + jnp.sum(passed & (error < jnp.pi / 4)).astype(jnp.float32),
            "turns_total": m["turns_total"] + jnp.sum(passed).astype(jnp.float32),
            "door_fraction": common.running_mean(m["door_fraction"], signals["door_frac"], steps),
            "steps": steps,
        }
        info = {"route_s": s, "goal_heading": self._command(task, s, pose[2])}
        return info, metrics, s >= length - cfg.finish_tolerance

    def _command(self, task: IndoorTask, s, heading):
        """The latest command issued by arc length ``s``, else the route's direction."""
        cfg = self.config
        issued = s >= task.junction_s - cfg.c - cfg.command_lead_s * cfg.fixed_speed
        latest = jnp.max(jnp.where(issued, jnp.arange(_NUM_JUNCTIONS), -1))
        route_heading = common.path_point(task.route, s + 0.5)[1]
        return jnp.where(latest >= 0, task.commands[jnp.maximum(latest, 0)], route_heading)


# -------------------------------------------------------------------------------------------- layout


def indoor_layout(cfg: IndoorConfig, seed: jax.Array) -> Scene:
    """Walls (fixed per config) and ``cfg.doors`` doors on random wall faces from ``seed``."""
    key = jax.random.wrap_key_data(jnp.asarray(seed, jnp.uint32))
    k_face, k_pos, k_col = jax.random.split(key, 3)
    walls = jnp.asarray(cfg.walls())
    faces = jnp.asarray(cfg.faces())
    usable = faces[:, 4] > cfg.door_width + 1.0
    # Longer faces get more doors: pick a face with probability proportional to its usable length.
    weight = jnp.where(usable, faces[:, 4] - cfg.door_width - 1.0, 0.0)
    f = jax.random.categorical(k_face, jnp.log(jnp.maximum(weight, 1e-9)), shape=(cfg.doors,))
    face = faces[f]
    along = 0.5 + 0.5 * cfg.door_width + jax.random.uniform(k_pos, (cfg.doors,)) * (face[:, 4] - cfg.door_width - 1.0)
    direction = face[:, 2:4]
    left = jnp.stack([-direction[:, 1], direction[:, 0]], -1)  # toward the corridor
    depth = 0.05  # the door's thickness; it stands door_proud out of the wall
    centre = face[:, :2] + along[:, None] * direction + (cfg.door_proud - depth / 2) * left
    yaw = jnp.arctan2(direction[:, 1], direction[:, 0])
    doors = jnp.stack([centre[:, 0], centre[:, 1], jnp.full((cfg.doors,), cfg.door_width / 2),
                       jnp.full((cfg.doors,), depth / 2), yaw, jnp.full((cfg.doors,), cfg.door_height)], -1)
    nw = walls.shape[0]
    shade = jax.random.uniform(k_col, (cfg.doors, 1), minval=0.85, maxval=1.15)
    door_col = jnp.clip(jnp.asarray([0.55, 0.3, 0.12]) * shade, 0.0, 1.0)
    a, b, c = cfg.half_x, cfg.half_y, cfg.c
    extent = max(a, b) + c + cfg.stub_length + cfg.wall_thickness
    scene = empty_scene(0, nw + cfg.doors, 1)
    return scene.replace(
        boxes=jnp.concatenate([walls, doors]).astype(jnp.float32),
        box_class=jnp.asarray([WALL] * nw + [DOOR] * cfg.doors, jnp.int32),
        box_color=jnp.concatenate([jnp.full((nw, 3), 0.86), door_col]).astype(jnp.float32),
        ground_class=jnp.asarray(FLOOR, jnp.int32),
        ground_color=jnp.asarray([0.5, 0.49, 0.47], jnp.float32),
        ceiling_height=jnp.asarray(cfg.ceiling_height, jnp.float32),
        bounds=jnp.asarray([-extent, -extent, extent, extent], jnp.float32),
    )
