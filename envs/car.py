"""The car: a planar MuJoCo chassis driven by a dynamic bicycle model, simulated with MJX.

Physics.  The chassis is a free planar body (slide x, slide y, hinge yaw) carrying one box geom.  Every
physics substep ``bicycle_forces`` turns the current velocity, the steering angle and the held drive
force into generalized forces (``qfrc_applied``) and ``mjx.step`` integrates them together with the
contact forces, so momentum is real (braking and turning take time) and the car cannot pass through an
obstacle.  Gravity plays no role on a flat world and is disabled; tyre loads are the static mg/2 per axle.

* Speed control (the paper's Bullet car): once per 0.25 s control step, per driven wheel,
  ``F = clip(speed_gain * (v_set - v), +-force_cap) * mass``, held over the substeps; the paper applies it to
  each of its 4 wheels, so the total is ``drive_wheels`` times that.  Half of it acts along the rear
  axle, half along the steered front wheels.
* Lateral tyre force per axle from the slip velocity ``v_lat`` across the wheel: a linear tyre
  ``F = -C_alpha * v_lat / max(|v_long|, slip_speed_floor)`` (``C_alpha`` in N/rad, so the slope is the
  cornering stiffness for small slip angles), saturated at ``friction * mg/2``.  Why it is evaluated
  implicitly (divided by ``1 + k dt / m_eff``): real tyres are far stiffer than an explicit 0.05 s step can
  integrate (the lateral time constant m*v/C is milliseconds at walking speed); the implicit form is the
  force that would remove the slip over one substep in the stiff limit, so it is stable for any
  stiffness and speed, and it reduces to the linear tyre when the tyre is soft.  ``m_eff`` is half the
  effective mass seen at the axle, so front and rear together cannot overshoot.

Contacts.  Only chassis/obstacle pairs exist (chassis contype=2 conaffinity=1, obstacles the reverse).
MJX runs a collision function for *every* candidate pair each substep, which dominated the cost, so the
compiled physics model holds only ``CarConfig.near_circles`` capsule slots and ``near_boxes`` box slots:
once per control step ``nearest_obstacles`` copies the nearest obstacles of the full scene (exact 2-D
distances) into those slots with ``envs.scene.update_model_geometry``.  This is exact while no more
obstacles than slots lie within reach of the car during one control step; ``reach`` bounds how far the
car can get and the step reports ``overflow`` when the slots did not cover everything within it.  The
cost of physics is then independent of the scene size.  Contacts are frictionless (condim 1): only the
normal force matters for a bumper, and it leaves one constraint row per contact point.

Bumper.  ``collision`` is True when any chassis contact penetrates (dist < 0) at any collision pass of
the control step.  MJX collides before it integrates, so the final position of a control step is
checked by ``footprint_overlap``, the same exact geometry in 2-D, so a crash is reported in the step it
happens.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from envs import base
from envs.scene import Scene, empty_scene, scene_to_mjcf, update_model_geometry

_FAR = 1e9  # distance of an unused obstacle slot (finite: no inf - inf)


@dataclasses.dataclass(frozen=True)
class CarConfig:
    """The car and its physics settings (hashable: one compiled step per config)."""

    half_length: float = 1.0  # chassis 2.0 m long (along the car's +x, its forward)
    half_width: float = 0.6  # 1.2 m wide
    half_height: float = 0.25  # 0.5 m tall, standing on the ground
    mass: float = 10.0
    front_axle: float = 0.5  # distance of the axles from the centre (the paper's wheels at +-0.5 m)
    rear_axle: float = 0.5
    speed_gain: float = 1.25  # 1/s, the paper's P gain
    force_cap: float = 0.5  # per driven wheel, in units of the mass (m/s^2)
    drive_wheels: int = 4
    cornering_stiffness: float = 500.0  # N/rad per axle
    friction: float = 1.0  # tyre friction coefficient: lateral force <= friction * m g / 2 per axle
    slip_speed_floor: float = 0.5  # m/s: slip angles use max(|v_long|, floor) (finite at standstill)
    substeps: int = 5  # physics steps per control step (paper: 5 x 0.05 s)
    # One Newton iteration with one line-search step: the few frictionless contact rows of a bumper
    # converge in it (the wall test in tests/test_car.py checks penetration and stopping), and it is
    # ~25 % faster than 2 / 4.
    solver_iterations: int = 1
    ls_iterations: int = 1
    # Obstacle slots of the physics model (see the module docstring): each slot costs a collision
    # function per substep, the bulk of a step's time.  A forest car touches at most a few trees and
    # two walls (a corner) within one control step; ``overflow`` reports when that was not enough.
    near_circles: int = 3
    near_boxes: int = 2
    max_speed: float = 10.0  # m/s; bounds the reach used to check that the slots suffice

    def __post_init__(self):
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps}")
        if min(self.half_length, self.half_width, self.half_height, self.mass) <= 0:
            raise ValueError("chassis sizes and mass must be positive")
        if self.near_circles < 0 or self.near_boxes < 0:
            raise ValueError("near_circles and near_boxes must be >= 0")

    @property
    def dt(self) -> float:
        return base.CONTROL_DT / self.substeps

    @property
    def inertia(self) -> float:
        """Yaw moment of inertia of the uniform box (kg m^2)."""
        return self.mass * ((2 * self.half_length) ** 2 + (2 * self.half_width) ** 2) / 12.0

    @property
    def max_accel(self) -> float:
        return self.drive_wheels * self.force_cap

    @property
    def radius(self) -> float:
        """Radius of the chassis footprint's bounding circle."""
        return math.hypot(self.half_length, self.half_width)

    def turning_radius(self, steer_deg: float) -> float:
        """Radius (m) of the circle the car's centre drives at a steering angle, slip-free (the kinematic
        bicycle: the rear axle turns on wheelbase / tan(steer), and the centre lies ``rear_axle`` ahead of it).
        1.80 m at the plan box's 30 degrees; the simulated car at low speed drives it within a few percent."""
        if not 0 < steer_deg < 90:
            raise ValueError(f"steer_deg must be in (0, 90) degrees, got {steer_deg}")
        rear = (self.front_axle + self.rear_axle) / math.tan(math.radians(steer_deg))
        return math.hypot(rear, self.rear_axle)

    def reach(self, speed: jax.Array) -> jax.Array:
        """How far from its centre the chassis can touch something within one control step."""
        v = jnp.minimum(jnp.abs(speed) + self.max_accel * base.CONTROL_DT, self.max_speed)
        return self.radius + v * base.CONTROL_DT + 0.1


@struct.dataclass
class CarState:
    """The car's physical state between control steps (MuJoCo joint coordinates)."""

    qpos: jax.Array  # f32[3]: x, y, yaw
    qvel: jax.Array  # f32[3]: world vx, vy, yaw rate


def car_xml(cfg: CarConfig, pose=(0.0, 0.0, 0.0)) -> str:
    """The chassis body at ``pose`` (x, y, yaw); its joints start at zero there.

    priority=1 makes the chassis's condim=1 win over the obstacles' default condim.
    """
    x, y, yaw = (float(v) for v in np.asarray(pose))
    return (
        f'    <body name="car" pos="{x:.6g} {y:.6g} {cfg.half_height:.6g}" euler="0 0 {math.degrees(yaw):.6g}">\n'
        '      <joint name="x" type="slide" axis="1 0 0"/>\n'
        '      <joint name="y" type="slide" axis="0 1 0"/>\n'
        '      <joint name="yaw" type="hinge" axis="0 0 1"/>\n'
        f'      <geom name="chassis" type="box" size="{cfg.half_length:.6g} {cfg.half_width:.6g} '
        f'{cfg.half_height:.6g}" mass="{cfg.mass:.6g}" contype="2" conaffinity="1" condim="1" priority="1" '
        'rgba="0.9 0.3 0.1 1"/>\n'
        '    </body>'
    )


def option_xml(cfg: CarConfig) -> str:
    """Solver settings for a planar car: everything a flat world does not need is switched off."""
    return (
        f'  <option timestep="{cfg.dt:.6g}" integrator="Euler" iterations="{cfg.solver_iterations}" '
        f'ls_iterations="{cfg.ls_iterations}" gravity="0 0 0">\n'
        '    <flag gravity="disable" eulerdamp="disable" frictionloss="disable" limit="disable" '
        'equality="disable" actuation="disable" clampctrl="disable" warmstart="disable"/>\n'
        '  </option>'
    )


def physics_mjcf(cfg: CarConfig, num_circles: int, num_boxes: int) -> str:
    """The compiled physics world: the car plus ``num_circles`` capsule and ``num_boxes`` box slots."""
    slots = empty_scene(num_circles, num_boxes, 1)
    return scene_to_mjcf(slots, car_xml=car_xml(cfg), extra_xml=option_xml(cfg), name="car_physics")


def full_mjcf(cfg: CarConfig, scene: Scene, pose=(0.0, 0.0, 0.0), name: str = "scene") -> str:
    """A whole scene with the car at ``pose`` (for MuJoCo's viewer and for ``mjx.ray`` comparisons)."""
    return scene_to_mjcf(scene, car_xml=car_xml(cfg, pose), extra_xml=option_xml(cfg), name=name)


class CarPhysics:
    """The compiled MJX car model and its pure step; one instance per (CarConfig, slot counts)."""

    def __init__(self, cfg: CarConfig, num_circles: int, num_boxes: int):
        # Never more slots than the scene family has obstacles of that kind.
        self.cfg = cfg
        self.num_circles = min(cfg.near_circles, num_circles)
        self.num_boxes = min(cfg.near_boxes, num_boxes)
        self.mj_model = mujoco.MjModel.from_xml_string(physics_mjcf(cfg, self.num_circles, self.num_boxes))
        self.model = mjx.put_model(self.mj_model, impl="jax")
        self.data0 = mjx.make_data(self.model)

    def init(self, pose: jax.Array) -> CarState:
        return CarState(qpos=jnp.asarray(pose, jnp.float32), qvel=jnp.zeros((3,), jnp.float32))

    def step(self, car: CarState, scene: Scene, steer_rad: jax.Array, speed_setpoint: jax.Array):
        """One control step (``CONTROL_DT``).  Returns ``(car, collision bool[], overflow bool[])``."""
        cfg = self.cfg
        near, overflow = nearest_obstacles(scene, car.qpos[:2], self.num_circles, self.num_boxes,
                                           cfg.reach(forward_speed(car)))
        model = update_model_geometry(self.model, near)
        drive = drive_force(cfg, forward_speed(car), speed_setpoint)
        data = self.data0.replace(qpos=car.qpos, qvel=car.qvel)

        def substep(d, _):
            frc = bicycle_forces(cfg, d.qpos, d.qvel, steer_rad, drive)
            d = mjx.step(model, d.replace(qfrc_applied=frc))
            return d, _penetrating(d)

        data, hits = jax.lax.scan(substep, data, None, length=cfg.substeps)
        qpos = data.qpos.at[2].set(base.wrap_angle(data.qpos[2]))
        # mjx.step collides *before* integrating, so its passes saw every position but the final one;
        # the exact footprint test covers that one (an extra MJX collision pass cost ~20 % per step).
        collision = jnp.any(hits) | footprint_overlap(cfg, qpos, near)
        return CarState(qpos=qpos, qvel=data.qvel), collision, overflow


def _penetrating(d) -> jax.Array:
    dist = d._impl.contact.dist  # MJX keeps a fixed-size contact list; inactive pairs have dist > 0
    return jnp.any(dist < 0) if dist.shape[0] else jnp.zeros((), bool)


def forward_speed(car: CarState) -> jax.Array:
    """Signed speed along the car's heading (what a wheel encoder measures)."""
    yaw = car.qpos[2]
    return car.qvel[0] * jnp.cos(yaw) + car.qvel[1] * jnp.sin(yaw)


def drive_force(cfg: CarConfig, speed: jax.Array, setpoint: jax.Array) -> jax.Array:
    """Total longitudinal force (N) of the P speed controller, held over one control step."""
    per_wheel = jnp.clip(cfg.speed_gain * (setpoint - speed), -cfg.force_cap, cfg.force_cap) * cfg.mass
    return cfg.drive_wheels * per_wheel


def bicycle_forces(cfg: CarConfig, qpos: jax.Array, qvel: jax.Array, steer: jax.Array, drive: jax.Array):
    """Generalized forces f32[3] (Fx, Fy world, yaw torque) of the tyres; see the module docstring."""
    yaw = qpos[2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    u = c * qvel[0] + s * qvel[1]  # body-frame forward velocity
    v = -s * qvel[0] + c * qvel[1]  # body-frame leftward velocity
    r = qvel[2]
    load = cfg.mass * 9.81 / 2  # static normal load per axle
    inertia = cfg.inertia

    def lateral(u_w, v_w, arm):
        k = cfg.cornering_stiffness / jnp.maximum(jnp.abs(u_w), cfg.slip_speed_floor)
        m_eff = 0.5 / (1.0 / cfg.mass + arm**2 / inertia)
        force = -k * v_w / (1.0 + k * cfg.dt / m_eff)
        return jnp.clip(force, -cfg.friction * load, cfg.friction * load)

    # Front wheels: velocity of the axle point expressed in the steered wheel frame.
    cd, sd = jnp.cos(steer), jnp.sin(steer)
    vf = v + cfg.front_axle * r
    lat_f = lateral(cd * u + sd * vf, -sd * u + cd * vf, cfg.front_axle)
    lat_r = lateral(u, v - cfg.rear_axle * r, cfg.rear_axle)
    long_f = long_r = 0.5 * drive
    fx = long_r + cd * long_f - sd * lat_f
    fy = lat_r + sd * long_f + cd * lat_f
    torque = cfg.front_axle * (sd * long_f + cd * lat_f) - cfg.rear_axle * lat_r
    return jnp.stack([c * fx - s * fy, s * fx + c * fy, torque])


# ------------------------------------------------------------------------------ obstacles near the car


def footprint_overlap(cfg: CarConfig, pose: jax.Array, scene: Scene) -> jax.Array:
    """bool[]: the chassis footprint at ``pose`` overlaps an obstacle of ``scene`` (exact, 2-D).

    Obstacles are vertical prisms standing on the ground and the chassis spans z in [0, 2 half_height],
    so overlapping footprints are exactly a 3-D penetration.
    """
    half = jnp.asarray([cfg.half_length, cfg.half_width], jnp.float32)
    car_rot = _rotation(pose[2])
    # Circles: distance from the centre (in the car frame) to the rectangle.
    c = scene.circles
    local = (c[:, :2] - pose[:2]) @ car_rot  # rows: centres in car coordinates
    gap = jnp.linalg.norm(jnp.maximum(jnp.abs(local) - half, 0.0), axis=-1)
    hit_circle = jnp.any((c[:, 2] > 0) & (gap < c[:, 2]))
    # Boxes: separating-axis test on the four edge normals of the two rectangles.
    b = scene.boxes
    box_rot = jax.vmap(_rotation)(b[:, 4])  # [Nb, 2, 2], columns are the box axes
    axes = jnp.concatenate([jnp.broadcast_to(car_rot.T, box_rot.shape), jnp.swapaxes(box_rot, 1, 2)], 1)
    centre_gap = jnp.abs(jnp.einsum("nkd,nd->nk", axes, b[:, :2] - pose[:2]))
    # A rectangle's half-extent along a unit axis a: sum over its own axes e of half_e * |a . e|.
    car_extent = jnp.abs(jnp.einsum("nkd,de->nke", axes, car_rot)) @ half
    box_extent = jnp.einsum("nke,ne->nk", jnp.abs(jnp.einsum("nkd,nde->nke", axes, box_rot)), b[:, 2:4])
    separated = jnp.any(centre_gap >= car_extent + box_extent, axis=-1)
    hit_box = jnp.any((b[:, 2] > 0) & ~separated)
    return hit_circle | hit_box


def _rotation(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def circle_distances(scene: Scene, xy: jax.Array) -> jax.Array:
    """f32[Nc]: distance from ``xy`` to each circle's edge (negative inside); unused slots are far."""
    c = scene.circles
    d = jnp.linalg.norm(c[:, :2] - xy, axis=-1) - c[:, 2]
    return jnp.where(c[:, 2] > 0, d, _FAR)


def box_distances(scene: Scene, xy: jax.Array) -> jax.Array:
    """f32[Nb]: distance from ``xy`` to each oriented box footprint (negative inside); unused far."""
    b = scene.boxes
    rel = xy - b[:, :2]
    cy, sy = jnp.cos(b[:, 4]), jnp.sin(b[:, 4])
    local = jnp.stack([cy * rel[:, 0] + sy * rel[:, 1], -sy * rel[:, 0] + cy * rel[:, 1]], -1)
    q = jnp.abs(local) - b[:, 2:4]
    outside = jnp.linalg.norm(jnp.maximum(q, 0.0), axis=-1)
    inside = jnp.minimum(jnp.max(q, axis=-1), 0.0)
    return jnp.where(b[:, 2] > 0, outside + inside, _FAR)


def nearest_obstacles(scene: Scene, xy: jax.Array, num_circles: int, num_boxes: int, reach: jax.Array):
    """The ``num_circles`` nearest circles and ``num_boxes`` nearest boxes as a small Scene.

    Returns ``(near, overflow)``; ``overflow`` is True when more obstacles than slots lie within
    ``reach`` of ``xy`` (the physics would then miss one).  Slots beyond the scene's obstacles stay
    unused.  Ground paint is irrelevant to physics and dropped (one empty patch keeps shapes valid).
    """
    near = empty_scene(num_circles, num_boxes, 1)
    overflow = jnp.zeros((), bool)
    for field, count, distances in (("circles", num_circles, circle_distances), ("boxes", num_boxes, box_distances)):
        if count:
            d = distances(scene, xy)
            neg, idx = jax.lax.top_k(-d, count)
            keep = -neg < _FAR
            near = near.replace(**{field: jnp.where(keep[:, None], getattr(scene, field)[idx], 0.0)})
            overflow |= jnp.sum(d < reach) > count
    return near, overflow
