"""The JAX camera against mjx.ray, its semantics, and the Scene -> MJCF builder."""
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from envs import scene as S
from envs.camera import FOREST_CAMERA, CameraConfig, camera_origin, mjx_ray_depth, pixel_rays, render


def forest_scene(seed: int = 0) -> S.Scene:
    """A small forest: 20 capsules on a jittered 5 m grid (tall trees and rocks lower than the ~1 m
    line of sight over them, so rays pass over some obstacles), 4 walls, 2 boxes (one lower than the
    camera, so its top is visible), 3 ground patches and 2 unused slots of each kind."""
    rng = np.random.default_rng(seed)
    scene = S.empty_scene(22, 8, 4)
    grid = [(x, y) for x in (-10, -5, 0, 5, 10) for y in (-10, -5, 0, 5, 10) if abs(x) + abs(y) < 20][:20]
    circles = np.zeros((22, 4), np.float32)
    for i, (x, y) in enumerate(grid):
        short = i % 4 < 2
        circles[i] = (x + rng.uniform(-1, 1), y + rng.uniform(-1, 1), rng.uniform(0.5, 1.0),
                      rng.uniform(0.2, 1.2) if short else rng.uniform(3, 12))
    boxes = np.zeros((8, 6), np.float32)
    boxes[0:4] = [(0, 13, 13.5, 0.5, 0, 3), (0, -13, 13.5, 0.5, 0, 3), (13, 0, 0.5, 13.5, 0, 3), (-13, 0, 0.5, 13.5, 0, 3)]
    boxes[4] = (2.5, 2.5, 1.0, 0.4, 0.6, 1.5)
    boxes[5] = (-2.5, 7.5, 0.8, 0.3, -0.3, 0.25)
    return scene.replace(
        circles=jnp.asarray(circles),
        circle_class=jnp.asarray(np.where(circles[:, 3] > 2, S.TREE, S.ROCK), jnp.int32),
        circle_color=jnp.asarray(rng.uniform(0.2, 0.8, (22, 3)), jnp.float32),
        boxes=jnp.asarray(boxes),
        box_class=jnp.asarray([S.WALL] * 4 + [S.CAR] * 4, jnp.int32),
        box_color=jnp.asarray(rng.uniform(0.2, 0.8, (8, 3)), jnp.float32),
        patches=jnp.asarray([[-3, -3, 3, 3], [-1, -20, 1, 20], [4, -2, 8, 2], [0, 0, 0, 0]], jnp.float32),
        patch_class=jnp.asarray([S.ROAD, S.LANE_LINE, S.SIDEWALK, S.ROAD], jnp.int32),
        patch_color=jnp.asarray([[0.3, 0.3, 0.3], [0.9, 0.9, 0.9], [0.6, 0.6, 0.55], [0, 0, 0]], jnp.float32),
        bounds=jnp.asarray([-12.5, -12.5, 12.5, 12.5], jnp.float32),
    )


def compile_scene(scene, **kw):
    model = mujoco.MjModel.from_xml_string(S.scene_to_mjcf(scene, **kw))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, mjx.put_model(model), mjx.put_data(model, data)


POSES = np.asarray([[-11.0, -11.0, 0.785], [0.3, -9.0, 1.57], [-6.0, -6.0, 0.8], [7.2, -2.0, 0.31],
                    [-3.7, 6.3, -1.24], [9.0, 9.0, -2.4]], np.float32)


# ------------------------------------------------------------------------------------------- MJCF


def test_mjcf_loads_in_mujoco_and_mjx_with_documented_ordering():
    scene = forest_scene()
    car = ('<body name="car" pos="0 0 0.25"><joint type="slide" axis="1 0 0"/>'
           '<geom name="chassis" type="box" size="1 0.6 0.25" contype="2" conaffinity="1"/></body>')
    model, mx, _ = compile_scene(scene, car_xml=car)
    nc, nb = scene.circles.shape[0], scene.boxes.shape[0]
    assert model.ngeom == 1 + nc + nb + 1  # ground, every slot (unused ones parked), the car
    assert model.nmat >= 1  # mjx.ray needs a material
    gid = lambda name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    assert gid("ground") == 0 and gid("circle0") == 1 and gid(f"box{nb - 1}") == nc + nb
    assert gid("chassis") == 1 + nc + nb
    obstacles = slice(1, 1 + nc + nb)
    assert np.all(model.geom_contype[obstacles] == 1) and np.all(model.geom_conaffinity[obstacles] == 2)
    assert model.geom_contype[0] == 0 and model.geom_conaffinity[0] == 0
    # Capsule 0 is vertical, its cylinder spans [0, height]; unused slots are parked below ground.
    r, h = np.asarray(scene.circles[0, 2:4])
    np.testing.assert_allclose(model.geom_size[1, :2], [r, h / 2], rtol=1e-5)
    np.testing.assert_allclose(model.geom_pos[1, 2], h / 2, rtol=1e-5)
    assert model.geom_pos[gid(f"circle{nc - 1}"), 2] == S.PARK_Z
    assert mx.ngeom == model.ngeom


def test_mjcf_unused_slots_omitted_and_ceiling():
    scene = forest_scene()
    used = int(np.sum(np.asarray(scene.circles[:, 2]) > 0) + np.sum(np.asarray(scene.boxes[:, 2]) > 0))
    model, _, _ = compile_scene(scene, keep_unused=False)
    assert model.ngeom == 1 + used
    model, _, _ = compile_scene(scene.replace(ceiling_height=jnp.float32(3.0)))
    ceiling = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "ceiling")
    assert ceiling == model.ngeom - 1 and model.geom_pos[ceiling, 2] == 3.0


def test_update_model_geometry_matches_a_fresh_compile():
    a, b = forest_scene(0), forest_scene(1)
    b = b.replace(circles=b.circles.at[3].set(0.0))  # a slot that becomes unused
    _, mx_a, _ = compile_scene(a)
    model_b, _, _ = compile_scene(b)
    updated = jax.jit(S.update_model_geometry)(mx_a, b)
    for field in ("geom_pos", "geom_size", "geom_quat", "geom_rgba", "geom_rbound", "geom_aabb"):
        new = np.asarray(getattr(updated, field))
        assert new.shape == np.shape(getattr(mx_a, field)), field
        np.testing.assert_allclose(new, getattr(model_b, field), atol=2e-6, err_msg=field)
    # Batched layouts: vmap over scenes with the model shared.
    scenes = jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)
    batched = jax.vmap(S.update_model_geometry, in_axes=(None, 0))(mx_a, scenes)
    assert batched.geom_pos.shape == (2,) + mx_a.geom_pos.shape


# ----------------------------------------------------------------------------------------- camera


def test_depth_matches_mjx_ray():
    """The acceptance criterion: within 1 cm of mjx.ray for >= 99 % of the pixels that hit a geom."""
    scene = forest_scene()
    car = '<body name="car"><geom type="box" size="1 0.6 0.25" pos="0 0 0.25" contype="2" conaffinity="1"/></body>'
    _, mx, dx = compile_scene(scene, car_xml=car)  # the car at the origin must be invisible to the rays
    cfg = FOREST_CAMERA
    poses = jnp.asarray(POSES)
    ours = np.asarray(jax.jit(jax.vmap(lambda p: render(scene, p, cfg)[2]))(poses))
    ref = np.asarray(jax.jit(jax.vmap(lambda p: mjx_ray_depth(mx, dx, p, cfg)))(poses))
    hits = (ref < cfg.far) | (ours < cfg.far)
    close = np.abs(ours - ref) < 0.01
    assert hits.mean() > 0.5
    assert close[hits].mean() >= 0.99, f"only {close[hits].mean():.4f} of hit pixels within 1 cm"


def test_depth_exact_over_short_obstacles_and_box_tops():
    """Rays passing over a low rock must see the tree behind it; a box lower than the camera shows
    its top.  (Covered statistically above; here every pixel of a close-up must agree.)"""
    scene = S.empty_scene(2, 1, 0)
    scene = scene.replace(circles=jnp.asarray([[3.0, 0.0, 0.6, 0.3], [6.0, 0.2, 0.8, 6.0]], jnp.float32),
                          boxes=jnp.asarray([[2.0, -1.5, 0.5, 0.5, 0.4, 0.2]], jnp.float32))
    _, mx, dx = compile_scene(scene)
    pose = jnp.asarray([0.0, 0.0, 0.0])
    cfg = dataclasses.replace(FOREST_CAMERA, width=48, height=27)
    ours = np.asarray(jax.jit(lambda p: render(scene, p, cfg)[2])(pose))
    ref = np.asarray(jax.jit(lambda p: mjx_ray_depth(mx, dx, p, cfg))(pose))
    np.testing.assert_allclose(ours, ref, atol=0.01)


def wall_ahead_scene(ceiling=np.inf):
    scene = S.empty_scene(1, 1, 1)
    return scene.replace(
        boxes=jnp.asarray([[6.0, 0.0, 0.5, 4.0, 0.0, 3.0]], jnp.float32),
        box_class=jnp.asarray([S.DOOR], jnp.int32),
        box_color=jnp.asarray([[0.6, 0.3, 0.2]], jnp.float32),
        patches=jnp.asarray([[0.0, -0.5, 5.0, 0.5]], jnp.float32),
        patch_class=jnp.asarray([S.ROAD], jnp.int32),
        patch_color=jnp.asarray([[0.3, 0.3, 0.3]], jnp.float32),
        ceiling_height=jnp.asarray(ceiling, jnp.float32),
    )


def test_semantics_outdoor():
    cfg = FOREST_CAMERA
    image, sem, depth = jax.jit(lambda p: render(wall_ahead_scene(), p, cfg))(jnp.zeros(3))
    sem = np.asarray(sem)
    h, w = sem.shape
    centre = slice(w // 2 - 2, w // 2 + 2)
    # The wall (5 m ahead of the camera, 8 m wide: it spans ~77 degrees) fills the centre columns
    # from the ground line up to its top; the road patch lies below the horizon in the centre.
    assert np.all(sem[h // 2 - 8:h // 2, centre] == S.DOOR)
    assert np.all(sem[-1, centre] == S.ROAD)
    assert np.all(sem[-1, :3] == S.GRASS) and np.all(sem[-1, -3:] == S.GRASS)
    assert np.all(sem[0, :] == S.SKY) and np.all(sem[0, :3] == S.SKY)
    _, dirs = pixel_rays(jnp.zeros(3), cfg)  # the wall face is at x = 5.5, the camera at x = 0.5
    np.testing.assert_allclose(np.asarray(depth)[h // 2 - 4, w // 2], 5.0 / dirs[h // 2 - 4, w // 2, 0], rtol=1e-5)
    assert np.all(np.asarray(depth)[0] == cfg.far)


def test_semantics_indoor_ceiling():
    _, sem, depth = jax.jit(lambda p: render(wall_ahead_scene(ceiling=2.5), p, FOREST_CAMERA))(jnp.zeros(3))
    sem, w = np.asarray(sem), sem.shape[1]
    assert np.all(sem[0, :] == S.CEILING)
    # Where the wall blocks the view there is no sky; beside it the ceiling meets the far plane
    # (nothing is drawn beyond ``far``, indoors too).
    assert not np.any(sem[:, w // 2 - 10:w // 2 + 10] == S.SKY)
    assert np.all(np.asarray(depth)[:, w // 2 - 10:w // 2 + 10] < FOREST_CAMERA.far)


def test_grayscale_shapes_and_dtypes():
    cfg = CameraConfig(width=100, height=50, grayscale=True)
    image, sem, depth = jax.jit(lambda p: render(forest_scene(), p, cfg))(jnp.asarray(POSES[1]))
    assert image.shape == (50, 100, 1) and image.dtype == jnp.uint8
    assert sem.shape == (50, 100) and sem.dtype == jnp.uint8
    assert depth.shape == (50, 100) and depth.dtype == jnp.float32
    assert cfg.image_shape == (50, 100, 1)


def test_jit_vmap_over_poses_and_scenes_no_nan():
    scene = forest_scene()
    rng = np.random.default_rng(0)
    poses = jnp.asarray(rng.uniform([-12, -12, -np.pi], [12, 12, np.pi], (8, 3)), jnp.float32)
    poses = poses.at[0].set(jnp.asarray([*np.asarray(scene.circles[0, :2]), 0.3]))  # camera inside a tree
    image, sem, depth = jax.jit(jax.vmap(lambda p: render(scene, p, FOREST_CAMERA)))(poses)
    assert image.shape == (8, 36, 64, 3) and sem.shape == (8, 36, 64) and depth.shape == (8, 36, 64)
    assert np.all(np.isfinite(np.asarray(depth))) and np.all(np.asarray(depth) >= 0)
    assert np.asarray(sem).max() < S.NUM_CLASSES
    # Different poses give different frames; a batch of scenes renders like one scene at a time.
    assert len({np.asarray(im).tobytes() for im in image}) == 8
    scenes = jax.tree.map(lambda x, y: jnp.stack([x, y]), forest_scene(0), forest_scene(1))
    both = jax.jit(jax.vmap(lambda sc, p: render(sc, p, FOREST_CAMERA)))(scenes, poses[:2])
    single = jax.jit(lambda p: render(forest_scene(1), p, FOREST_CAMERA))(poses[1])
    np.testing.assert_array_equal(np.asarray(both[1][1]), np.asarray(single[1]))


def test_empty_scene_and_motion_texture():
    scene = S.empty_scene(0, 0, 0)
    rend = jax.jit(lambda p: render(scene, p, FOREST_CAMERA))
    a, sem, depth = rend(jnp.asarray([0.0, 0.0, 0.0]))
    b, _, _ = rend(jnp.asarray([0.3, 0.0, 0.0]))
    assert set(np.unique(np.asarray(sem))) == {S.SKY, S.GRASS}
    # The ground texture moves with the car: plain ground alone shows ego-motion.
    assert np.abs(np.asarray(a, np.int32) - np.asarray(b, np.int32)).sum() > 0


def test_pixel_rays_camera_model():
    cfg = FOREST_CAMERA
    pose = jnp.asarray([1.0, 2.0, np.pi / 2])
    origin, dirs = pixel_rays(pose, cfg)
    np.testing.assert_allclose(origin, [1.0, 2.5, 0.375], atol=1e-6)
    np.testing.assert_allclose(camera_origin(pose, cfg), origin)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-6)
    # Facing +y, the image's left edge looks toward -x (the car's left) and the right edge toward +x.
    assert dirs[18, 0, 0] < 0 and dirs[18, -1, 0] > 0
    # Columns are vertical planes: every pixel of a column has the same azimuth.
    az = np.arctan2(dirs[..., 1], dirs[..., 0])
    np.testing.assert_allclose(az - az[:1], 0.0, atol=1e-6)
    # The centre row looks pitch_deg down (the paper: at the ground 6 m ahead of the car centre).
    centre_elev = np.degrees(np.arcsin((dirs[17, 32, 2] + dirs[18, 32, 2]) / 2))
    assert abs(centre_elev + cfg.pitch_deg) < 1.5
    assert abs(cfg.pitch_deg - 3.9) < 0.05


def test_cylindrical_camera_columns_at_equal_angles_and_depth_matches_mjx_ray():
    """A 240-degree cylindrical camera: equal column azimuths, and the renderer still agrees with mjx.ray."""
    cfg = dataclasses.replace(FOREST_CAMERA, projection="cylindrical", hfov_deg=240.0, width=48, height=18)
    _, dirs = pixel_rays(jnp.zeros(3), cfg)
    az = np.unwrap(np.arctan2(dirs[0, :, 1], dirs[0, :, 0]))
    np.testing.assert_allclose(np.diff(az), -np.radians(240.0) / 48, atol=1e-5)  # left to right
    np.testing.assert_allclose(az[0], np.radians(120.0 - 2.5), atol=1e-5)
    # Rows: one slope per row in every column (vertical world lines stay vertical).
    slope = dirs[..., 2] / np.linalg.norm(dirs[..., :2], axis=-1)
    np.testing.assert_allclose(slope - slope[:, :1], 0.0, atol=1e-6)
    scene = forest_scene()
    _, mx, dx = compile_scene(scene)
    poses = jnp.asarray(POSES[:3])
    ours = np.asarray(jax.jit(jax.vmap(lambda p: render(scene, p, cfg)[2]))(poses))
    ref = np.asarray(jax.jit(jax.vmap(lambda p: mjx_ray_depth(mx, dx, p, cfg)))(poses))
    hits = (ref < cfg.far) | (ours < cfg.far)
    assert hits.mean() > 0.5
    assert (np.abs(ours - ref) < 0.01)[hits].mean() >= 0.99


def test_cylindrical_camera_sees_beside_the_car():
    """A post 2 m to the car's left: outside the paper's 120-degree view, inside a 200-degree cylinder,
    in the column of azimuth +90 degrees."""
    scene = S.empty_scene(1, 0, 0)
    scene = scene.replace(circles=jnp.asarray([[0.5, 2.0, 0.3, 2.0]], jnp.float32))
    pose = jnp.zeros(3)
    assert not np.any(np.asarray(render(scene, pose, FOREST_CAMERA)[1]) == S.TREE)
    wide = dataclasses.replace(FOREST_CAMERA, projection="cylindrical", hfov_deg=200.0)
    seen = np.flatnonzero((np.asarray(render(scene, pose, wide)[1]) == S.TREE).any(axis=0))
    azimuth = 100.0 - (seen + 0.5) * 200.0 / 64  # degrees left of the heading, per column
    assert seen.size and np.all(np.abs(azimuth - 90.0) < 12)


def test_camera_config_rejects_bad_projection_and_field_of_view():
    with pytest.raises(ValueError, match="projection"):
        CameraConfig(projection="fisheye")
    with pytest.raises(ValueError, match="hfov_deg.*180"):
        CameraConfig(hfov_deg=190.0)
    with pytest.raises(ValueError, match="hfov_deg.*360"):
        CameraConfig(projection="cylindrical", hfov_deg=400.0)


def test_grayscale_is_the_papers_weighting_of_the_colour_image():
    # A grayscale camera renders one channel with the colours projected by the paper's weights; it must
    # be the weighting of the RGB image of the same view (up to the rounding of each 8-bit channel).
    scene = forest_scene()
    rgb_cfg = dataclasses.replace(FOREST_CAMERA, width=48, height=24)
    gray_cfg = dataclasses.replace(rgb_cfg, grayscale=True)
    for pose in POSES[:3]:
        rgb, sem_rgb, depth_rgb = render(scene, pose, rgb_cfg)
        gray, sem_gray, depth_gray = render(scene, pose, gray_cfg)
        expected = np.asarray(rgb, np.float64) @ np.asarray([0.299, 0.587, 0.114])
        assert np.abs(np.asarray(gray[..., 0], np.float64) - expected).max() <= 1.0
        np.testing.assert_array_equal(sem_rgb, sem_gray)
        np.testing.assert_array_equal(depth_rgb, depth_gray)
        # The channels are distinct and in order: the scene's grass ground is greener than it is red.
        ground = np.asarray(sem_rgb) == S.GRASS
        if ground.any():
            assert np.asarray(rgb)[ground][:, 1].mean() > np.asarray(rgb)[ground][:, 0].mean()


def test_many_ground_patches_table_lookup_equals_select_chains(monkeypatch):
    # Above camera._GATHER_PATCHES patches the renderer tests them on the rows below the horizon only
    # and looks class and colour up in a table; it must draw exactly what the select chains draw.
    from envs import camera

    rng = np.random.default_rng(3)
    num = camera._GATHER_PATCHES + 6
    lo = rng.uniform(-12, 8, (num, 2))
    patches = np.concatenate([lo, lo + rng.uniform(0.3, 6, (num, 2))], 1).astype(np.float32)
    scene = forest_scene().replace(
        patches=jnp.asarray(patches), patch_class=jnp.asarray(rng.integers(1, 6, num), jnp.int32),
        patch_color=jnp.asarray(rng.uniform(0, 1, (num, 3)), jnp.float32))
    poses = jnp.asarray(POSES)
    table = jax.jit(jax.vmap(lambda p: render(scene, p, FOREST_CAMERA)))(poses)
    monkeypatch.setattr(camera, "_GATHER_PATCHES", num)  # select chains on every row
    chains = jax.jit(jax.vmap(lambda p: render(scene, p, FOREST_CAMERA)))(poses)
    assert len(np.unique(np.asarray(table[1]))) > 4  # several paint classes are in view
    for a, b in zip(table, chains):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
