"""The MJX car (envs/car.py): speed control, turning radius, walls, the bumper and its geometry.

One compiled rollout (a fixed number of control steps, every other input as data) serves every driving
test, so the module pays for one MJX compilation.
"""
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from envs import car as carlib
from envs.scene import WALL, empty_scene

STEPS = 40  # 10 s of driving
CFG = carlib.CarConfig()
WALL_X = 10.0  # a wall's face at x = 9.5 (box centre 10, half thickness 0.5)


def _scene():
    scene = empty_scene(3, 2, 1)
    return scene.replace(
        circles=scene.circles.at[0].set(jnp.asarray([-30.0, 30.0, 0.8, 3.0])),  # far from every test
        boxes=scene.boxes.at[0].set(jnp.asarray([WALL_X, 0.0, 0.5, 5.0, 0.0, 2.0])),
        box_class=scene.box_class.at[0].set(WALL),
    )


@pytest.fixture(scope="module")
def drive():
    physics = carlib.CarPhysics(CFG, 3, 2)
    scene = _scene()

    @jax.jit
    def roll(pose, steer_deg, speed):
        def body(car, _):
            car, collision, overflow = physics.step(car, scene, jnp.deg2rad(steer_deg), speed)
            return car, (car.qpos, car.qvel, carlib.forward_speed(car), collision, overflow)

        return jax.lax.scan(body, physics.init(pose), None, length=STEPS)[1]

    def run(pose, steer_deg, speed):
        out = roll(jnp.asarray(pose, jnp.float32), jnp.float32(steer_deg), jnp.float32(speed))
        return [np.asarray(x) for x in out]

    return run


def test_straight_driving_reaches_the_setpoint(drive):
    qpos, qvel, speed, collision, overflow = drive((-20.0, -20.0, 0.3), 0.0, 2.0)
    assert abs(speed[12] - 2.0) < 0.02  # after 3 s
    assert np.all(np.abs(speed[12:] - 2.0) < 0.02)
    np.testing.assert_allclose(qpos[:, 2], 0.3, atol=1e-4)  # straight: the heading does not change
    direction = np.diff(qpos[:, :2], axis=0)
    np.testing.assert_allclose(np.arctan2(direction[:, 1], direction[:, 0]), 0.3, atol=1e-3)
    # Momentum: the P controller's force is capped, so reaching 2 m/s from rest takes more than a step.
    assert speed[0] < 1.0
    assert not collision.any() and not overflow.any()


def test_constant_steer_gives_the_kinematic_circle(drive):
    steer = 20.0
    qpos, _, speed, collision, _ = drive((-20.0, -20.0, 0.0), steer, 1.0)
    xy = qpos[8:, :2]  # after the speed settled
    # Least-squares circle: x^2 + y^2 = 2 a x + 2 b y + c.
    design = np.c_[2 * xy, np.ones(len(xy))]
    (a, b, c), *_ = np.linalg.lstsq(design, (xy**2).sum(1), rcond=None)
    radius = math.sqrt(c + a * a + b * b)
    # Kinematic bicycle: the rear axle turns on L / tan(delta); the centre lies half a wheelbase ahead.
    expected = CFG.turning_radius(steer)
    assert expected == pytest.approx(math.hypot((CFG.front_axle + CFG.rear_axle) / math.tan(math.radians(steer)),
                                                CFG.rear_axle))
    assert abs(radius - expected) / expected < 0.05
    assert np.all(np.diff(np.unwrap(qpos[:, 2])) > 0)  # positive steer turns left (CCW)
    assert not collision.any()


def test_driving_into_a_wall_raises_collision_and_stops(drive):
    qpos, qvel, speed, collision, _ = drive((0.0, 0.0, 0.0), 0.0, 3.0)
    face = WALL_X - 0.5
    first = int(np.argmax(collision))
    assert collision.any()
    # The bumper fires in the step the chassis reaches the wall, not later.
    front = qpos[:, 0] + CFG.half_length
    assert front[first] > face - 1e-3 and (first == 0 or front[first - 1] < face)
    # It cannot pass through: the chassis stays within a few centimetres of the face, and stops.
    assert np.all(front < face + 0.05)
    assert np.all(np.abs(speed[first + 4:]) < 0.05)


def test_sensors_match_the_true_state(drive):
    qpos, qvel, speed, _, _ = drive((-20.0, -20.0, 2.0), 15.0, 1.5)
    heading = qpos[:, 2]
    assert np.all(np.abs(heading) <= math.pi)  # wrapped
    forward = qvel[:, 0] * np.cos(heading) + qvel[:, 1] * np.sin(heading)
    np.testing.assert_allclose(speed, forward, atol=1e-5)
    # Little side slip at low speed: the velocity points (nearly) where the car heads.
    np.testing.assert_allclose(np.linalg.norm(qvel[10:, :2], axis=-1), np.abs(speed[10:]), rtol=0.02)


def _mujoco_penetration(scene, pose) -> bool:
    """MuJoCo's own (C) collision detection on the full scene with the car at ``pose``."""
    model = mujoco.MjModel.from_xml_string(carlib.full_mjcf(CFG, scene, pose))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return any(data.contact[i].dist < 0 for i in range(data.ncon))


def test_footprint_overlap_agrees_with_mujoco_contacts():
    scene = empty_scene(2, 2, 1)
    scene = scene.replace(
        circles=scene.circles.at[0].set(jnp.asarray([3.0, 0.0, 0.7, 2.0])),
        boxes=scene.boxes.at[0].set(jnp.asarray([-3.0, 1.0, 1.5, 0.4, 0.6, 2.0])),
    )
    rng = np.random.default_rng(0)
    poses = np.c_[rng.uniform(-5.5, 5.5, (120, 2)), rng.uniform(-math.pi, math.pi, 120)]
    overlap = jax.jit(jax.vmap(lambda p: carlib.footprint_overlap(CFG, p, scene)))(jnp.asarray(poses, jnp.float32))
    expected = np.array([_mujoco_penetration(scene, p) for p in poses])
    assert expected.sum() > 10 and (~expected).sum() > 10  # both cases are exercised
    np.testing.assert_array_equal(np.asarray(overlap), expected)


def test_nearest_obstacles_and_overflow():
    scene = empty_scene(5, 2, 1)
    xs = jnp.asarray([1.5, 3.0, 6.0, 9.0, 0.0])
    circles = jnp.stack([xs, jnp.zeros(5), jnp.full(5, 0.5), jnp.ones(5)], -1).at[4, 2].set(0.0)  # slot 4 unused
    scene = scene.replace(circles=circles, boxes=scene.boxes.at[1].set(jnp.asarray([0.0, -4.0, 5.0, 0.5, 0.0, 1.0])))
    near, overflow = carlib.nearest_obstacles(scene, jnp.zeros(2), 2, 2, jnp.asarray(3.0))
    np.testing.assert_allclose(np.asarray(near.circles[:, 0]), [1.5, 3.0])
    assert float(near.boxes[0, 1]) == -4.0 and float(near.boxes[1, 2]) == 0.0  # the empty box slot stays unused
    assert not bool(overflow)
    _, overflow = carlib.nearest_obstacles(scene, jnp.zeros(2), 1, 2, jnp.asarray(3.0))
    assert bool(overflow)  # two circles within reach, one slot
