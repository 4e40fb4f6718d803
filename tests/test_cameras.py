"""cusgs_jax.cameras: look_at, orbit, slerp paths, camera_path and COLMAP/Blender poses (OpenCV axes, world→camera)."""

import pathlib

import numpy as np
import pytest

from cusgs_jax import cameras as cams
from cusgs_jax.data.frames import opengl_c2w_to_viewmat
from cusgs_jax.data.normalize import WorldTransform
from cusgs_jax.types import Camera

W, H = 64, 48


def project(camera, point):
    """(pixel [2], depth) of a world point [3] seen by one camera (float64)."""
    viewmat, K = np.asarray(camera.world_to_camera, np.float64), np.asarray(camera.K, np.float64)
    x = viewmat[:3, :3] @ np.asarray(point, np.float64) + viewmat[:3, 3]
    uvw = K @ x
    return uvw[:2] / uvw[2], x[2]


def center_of(viewmat):
    viewmat = np.asarray(viewmat, np.float64)
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


def axis_angle(axis, angle):
    """[3, 3] Rodrigues rotation by ``angle`` radians about unit ``axis``."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def random_rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def assert_rotation(rot, atol=1e-5):
    rot = np.asarray(rot, np.float64)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=atol)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=atol)


# ---------------------------------------------------------------- pinhole_K, look_at


def test_pinhole_K_field_of_view():
    K = cams.pinhole_K(W, H, fov_y_degrees=60.0)
    assert K.shape == (3, 3) and K.dtype == np.float32
    # the top and bottom image rows are at ±fov/2
    assert np.degrees(2 * np.arctan(0.5 * H / K[1, 1])) == pytest.approx(60.0, rel=1e-6)
    assert K[0, 0] == K[1, 1] and (K[0, 2], K[1, 2]) == (W / 2, H / 2)


@pytest.mark.parametrize("eye,target,up", [([0.3, -2.0, 0.5], [0.1, 0.2, -0.3], [0, 0, 1]),
                                           ([1.0, 1.0, 1.0], [-0.5, 0.2, 0.0], [0.2, -1.0, 0.3]),
                                           ([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0, -1, 0])])
def test_look_at_target_on_optical_axis_and_up_is_image_minus_y(eye, target, up):
    camera = cams.look_at(eye, target, up, width=W, height=H, fov_y_degrees=45.0)
    assert camera.world_to_camera.shape == (4, 4) and camera.K.shape == (3, 3)
    assert (camera.width, camera.height) == (W, H)
    viewmat = np.asarray(camera.world_to_camera, np.float64)
    assert_rotation(viewmat[:3, :3])
    np.testing.assert_allclose(center_of(viewmat), eye, atol=1e-5)
    pixel, depth = project(camera, target)
    np.testing.assert_allclose(pixel, [W / 2, H / 2], atol=1e-3)
    assert depth == pytest.approx(np.linalg.norm(np.subtract(target, eye)), rel=1e-5)
    # a point a little "up" from the target is above it in the image (smaller y), in the same column
    # when up is perpendicular to the view direction, and the up vector's image direction is exactly -y
    forward = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    up_perp = np.asarray(up, np.float64) - (np.asarray(up, np.float64) @ forward) * forward
    up_perp /= np.linalg.norm(up_perp)
    above, _ = project(camera, np.asarray(target) + 0.05 * up_perp)
    assert above[1] < H / 2 - 0.1
    assert above[0] == pytest.approx(W / 2, abs=1e-3)
    np.testing.assert_allclose(viewmat[1, :3], -up_perp, atol=1e-6)  # camera +y (image down) = -up
    # right-handed OpenCV axes: +x (image right) = forward × up... = down × forward
    np.testing.assert_allclose(viewmat[0, :3], np.cross(viewmat[1, :3], viewmat[2, :3]), atol=1e-6)


def test_look_at_explicit_K_is_used():
    K = np.array([[30.0, 0, 20.0], [0, 31.0, 10.0], [0, 0, 1]])
    camera = cams.look_at([0, -2, 0], [0, 0, 0], width=40, height=30, K=K)
    np.testing.assert_array_equal(np.asarray(camera.K), K.astype(np.float32))
    pixel, _ = project(camera, [0, 0, 0])
    np.testing.assert_allclose(pixel, [20.0, 10.0], atol=1e-4)  # the principal point, not the image centre


# ---------------------------------------------------------------- orbit


@pytest.mark.parametrize("up,elevation", [((0.0, 0.0, 1.0), 20.0), ((0.3, -1.0, 0.2), -35.0), ((1.0, 0, 0), 0.0)])
def test_orbit_circle_looking_at_centre(up, elevation):
    center, radius, frames = np.array([0.4, -0.2, 1.1]), 2.5, 7
    path = cams.orbit(center, radius, frames, up=up, elevation_degrees=elevation, width=W, height=H)
    viewmats = np.asarray(path.world_to_camera, np.float64)
    assert viewmats.shape == (frames, 4, 4) and path.K.shape == (frames, 3, 3) and (path.width, path.height) == (W, H)
    unit_up = np.asarray(up) / np.linalg.norm(up)
    offsets = np.stack([center_of(v) for v in viewmats]) - center
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=-1), radius, rtol=1e-5)
    # elevation above the plane normal to up
    np.testing.assert_allclose(np.degrees(np.arcsin(offsets @ unit_up / radius)), elevation, atol=1e-3)
    for v in range(frames):
        pixel, depth = project(Camera(path.K[v], path.world_to_camera[v], W, H), center)
        np.testing.assert_allclose(pixel, [W / 2, H / 2], atol=1e-3)
        assert depth == pytest.approx(radius, rel=1e-5)
        assert_rotation(viewmats[v, :3, :3])
        assert viewmats[v, 1, :3] @ unit_up < 0  # image up is the orbit's up side
    # evenly spaced in angle about up: consecutive in-plane directions 360°/frames apart, same turning sense
    flat = offsets - np.outer(offsets @ unit_up, unit_up)
    flat /= np.linalg.norm(flat, axis=-1, keepdims=True)
    nxt = np.roll(flat, -1, axis=0)
    signed = np.degrees(np.arctan2(np.cross(flat, nxt) @ unit_up, np.sum(flat * nxt, axis=-1)))
    np.testing.assert_allclose(np.abs(signed), 360.0 / frames, atol=1e-3)
    assert len(set(np.sign(signed))) == 1


def test_orbit_rejects_bad_arguments():
    with pytest.raises(ValueError, match="frames"):
        cams.orbit([0, 0, 0], 1.0, 0)
    with pytest.raises(ValueError, match="radius"):
        cams.orbit([0, 0, 0], 0.0, 4)


# ---------------------------------------------------------------- interpolate_path


def keys_rotated(theta, axis, *, c0=(0.1, -0.4, 2.0), c1=(1.2, 0.3, -0.5), rot0=None):
    """Two key cameras: the second's camera→world rotation is the first's (``rot0``) rotated by ``theta`` about
    ``axis``."""
    rot0 = random_rotation(3) if rot0 is None else rot0  # camera→world of key 0
    rot1 = axis_angle(axis, theta) @ rot0
    mats = []
    for rot, c in ((rot0, c0), (rot1, c1)):
        m = np.eye(4)
        m[:3, :3] = rot.T
        m[:3, 3] = -rot.T @ np.asarray(c)
        mats.append(m)
    K0, K1 = cams.pinhole_K(W, H, 40.0), cams.pinhole_K(W, H, 70.0)
    keys = Camera(np.stack([K0, K1]), np.stack(mats).astype(np.float32), W, H)
    return keys, rot0, np.asarray(c0), np.asarray(c1), K0, K1


@pytest.mark.parametrize("theta_degrees", [100.0, 30.0, 170.0, 0.01])
def test_interpolate_path_is_slerp_and_linear(theta_degrees):
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    theta = np.radians(theta_degrees)
    keys, rot0, c0, c1, K0, K1 = keys_rotated(theta, axis)
    frames = 5
    path = cams.interpolate_path(keys, frames)
    viewmats = np.asarray(path.world_to_camera, np.float64)
    assert viewmats.shape == (frames, 4, 4) and path.K.shape == (frames, 3, 3) and (path.width, path.height) == (W, H)
    np.testing.assert_allclose(viewmats[0], np.asarray(keys.world_to_camera[0]), atol=1e-6)
    np.testing.assert_allclose(viewmats[-1], np.asarray(keys.world_to_camera[1]), atol=1e-6)
    for f, t in enumerate(np.linspace(0.0, 1.0, frames)):
        assert_rotation(viewmats[f, :3, :3])
        np.testing.assert_allclose(viewmats[f, 3], [0, 0, 0, 1])
        expected_rot_cw = axis_angle(axis, t * theta) @ rot0  # slerp: rotated by t·θ about the same axis
        np.testing.assert_allclose(viewmats[f, :3, :3], expected_rot_cw.T, atol=2e-6)
        np.testing.assert_allclose(center_of(viewmats[f]), (1 - t) * c0 + t * c1, atol=2e-6)
        np.testing.assert_allclose(np.asarray(path.K[f]), (1 - t) * K0 + t * K1, rtol=1e-6)


@pytest.mark.parametrize("start,theta,half", [(0.0, 270.0, -45.0), (170.0, 90.0, 45.0), (170.0, -120.0, -60.0)])
def test_interpolate_path_takes_the_shorter_arc(start, theta, half):
    # start 170°: the keys' quaternions (w >= 0 each) have a negative dot product, so only the sign flip of slerp
    # keeps the path on the short arc
    axis = np.array([1.0, 0.0, 0.0])
    keys, rot0, *_ = keys_rotated(np.radians(theta), axis, rot0=axis_angle(axis, np.radians(start)))
    mid = np.asarray(cams.interpolate_path(keys, 3).world_to_camera[1], np.float64)
    np.testing.assert_allclose(mid[:3, :3], (axis_angle(axis, np.radians(half)) @ rot0).T, atol=2e-6)


def test_interpolate_path_passes_through_every_key():
    eyes = [[2.0, 0.0, 0.5], [0.0, 2.0, 0.2], [-2.0, 0.3, 0.0], [0.0, -2.0, 0.8]]
    keys = cams.stack_cameras([cams.look_at(e, [0, 0, 0], width=W, height=H) for e in eyes])
    path = cams.interpolate_path(keys, 3 * (len(eyes) - 1) + 1)  # keys land on frames 0, 3, 6, 9
    for k in range(len(eyes)):
        np.testing.assert_allclose(np.asarray(path.world_to_camera[3 * k]), np.asarray(keys.world_to_camera[k]),
                                   atol=1e-6)
    for v in np.asarray(path.world_to_camera, np.float64):
        assert_rotation(v[:3, :3])


def test_interpolate_path_rejects_bad_arguments():
    keys = cams.stack_cameras([cams.look_at([0, -2, 0], [0, 0, 0]), cams.look_at([2, 0, 0], [0, 0, 0])])
    with pytest.raises(ValueError, match="frames"):
        cams.interpolate_path(keys, 1)
    with pytest.raises(ValueError, match="two or more"):
        cams.interpolate_path(cams.stack_cameras([cams.look_at([0, -2, 0], [0, 0, 0])]), 5)
    with pytest.raises(ValueError, match="batched"):
        cams.interpolate_path(cams.look_at([0, -2, 0], [0, 0, 0]), 5)  # one unbatched camera


# ---------------------------------------------------------------- camera_path


def training_ring(n=6, radius=1.7, center=(0.2, 0.1, -0.3), width=W, height=H):
    return cams.orbit(center, radius, n, up=(0.0, 0.0, 1.0), elevation_degrees=0.0, width=width, height=height,
                      fov_y_degrees=55.0)


def test_camera_path_orbit_recovers_a_ring_of_cameras():
    # cameras on a circle looking at its centre: the path's orbit is that circle (same centre, radius, up, phase)
    ring = training_ring()
    path = cams.camera_path(ring, "orbit", 6, elevation_degrees=0.0)
    assert (path.width, path.height) == (W, H)
    np.testing.assert_allclose(np.asarray(path.world_to_camera), np.asarray(ring.world_to_camera), atol=2e-5)
    np.testing.assert_allclose(np.asarray(path.K), np.asarray(ring.K), rtol=1e-5)


@pytest.mark.parametrize("kind", ["orbit", "interpolate"])
def test_camera_path_shapes_and_size(kind):
    ring = training_ring()
    path = cams.camera_path(ring, kind, 9, width=2 * W, height=H // 2)
    assert path.world_to_camera.shape == (9, 4, 4) and path.K.shape == (9, 3, 3)
    assert (path.width, path.height) == (2 * W, H // 2)
    K = np.asarray(path.K)
    np.testing.assert_allclose(K[:, 0, 2], W, rtol=1e-6)  # the principal point of the new size
    np.testing.assert_allclose(K[:, 1, 2], H / 4, rtol=1e-6)
    for v in np.asarray(path.world_to_camera, np.float64):
        assert_rotation(v[:3, :3])
    if kind == "interpolate":
        np.testing.assert_allclose(np.asarray(path.world_to_camera[0]), np.asarray(ring.world_to_camera[0]),
                                   atol=1e-6)
        np.testing.assert_allclose(np.asarray(path.world_to_camera[-1]), np.asarray(ring.world_to_camera[-1]),
                                   atol=1e-6)
        np.testing.assert_allclose(K[:, 0, 0], 2 * np.asarray(ring.K)[0, 0, 0], rtol=1e-6)  # rescaled focal
        np.testing.assert_allclose(K[:, 1, 1], 0.5 * np.asarray(ring.K)[0, 1, 1], rtol=1e-6)
    else:
        # the orbit keeps the vertical field of view of the training cameras
        fov = np.degrees(2 * np.arctan(0.5 * (H // 2) / K[:, 1, 1]))
        np.testing.assert_allclose(fov, 55.0, rtol=1e-5)


def test_camera_path_rejects_a_bad_kind_and_frames():
    ring = training_ring()
    with pytest.raises(ValueError, match="kind='spiral'"):
        cams.camera_path(ring, "spiral", 5)
    with pytest.raises(ValueError, match="frames"):
        cams.camera_path(ring, "interpolate", 1)


# ---------------------------------------------------------------- invalid arguments


@pytest.mark.parametrize("fov", [0.0, 180.0, -10.0, 270.0])
def test_field_of_view_out_of_range(fov):
    with pytest.raises(ValueError, match="fov_y_degrees"):
        cams.pinhole_K(W, H, fov)
    with pytest.raises(ValueError, match="fov_y_degrees"):
        cams.look_at([0, -2, 0], [0, 0, 0], fov_y_degrees=fov)


def test_look_at_degenerate_directions():
    with pytest.raises(ValueError, match="same point"):
        cams.look_at([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="parallel to up"):
        cams.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="parallel to up"):
        cams.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], up=(0.0, 0.0, -3.0))


def test_stack_cameras_needs_one_size():
    with pytest.raises(ValueError, match="one image size"):
        cams.stack_cameras([cams.look_at([0, -2, 0], [0, 0, 0], width=40, height=30),
                            cams.look_at([2, 0, 0], [0, 0, 0], width=40, height=31)])
    with pytest.raises(ValueError, match="one or more"):
        cams.stack_cameras([])


# ---------------------------------------------------------------- from_colmap, from_blender

WORLD = WorldTransform(0.37, (1.5, -2.0, 0.75), tuple(tuple(row) for row in random_rotation(11)))


def colmap_viewmats(n=3, seed=5):
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    for b in range(n):
        out[b, :3, :3] = random_rotation(seed + b)
        out[b, :3, 3] = rng.normal(size=3) * 2.0
    return out


def test_from_colmap_equals_the_world_transform():
    viewmats = colmap_viewmats()
    K = cams.pinhole_K(W, H, 50.0)
    batch = cams.from_colmap(WORLD, viewmats, K, W, H)
    assert batch.world_to_camera.shape == (3, 4, 4) and batch.K.shape == (3, 3, 3)
    assert (batch.width, batch.height) == (W, H)
    np.testing.assert_array_equal(np.asarray(batch.world_to_camera), WORLD.viewmats(viewmats).astype(np.float32))
    np.testing.assert_array_equal(np.asarray(batch.K), np.broadcast_to(K, (3, 3, 3)))
    one = cams.from_colmap(WORLD, viewmats[1], K, W, H)
    assert one.world_to_camera.shape == (4, 4) and one.K.shape == (3, 3)
    np.testing.assert_array_equal(np.asarray(one.world_to_camera), np.asarray(batch.world_to_camera[1]))


def test_from_colmap_sees_a_point_where_the_colmap_camera_does():
    viewmats = colmap_viewmats()
    points = np.random.default_rng(2).normal(size=(10, 3)) * 3.0  # in the COLMAP frame
    moved = cams.from_colmap(WORLD, viewmats, cams.pinhole_K(W, H), W, H)
    normalized = WORLD.to_normalized(points)
    for b in range(len(viewmats)):
        x = points @ viewmats[b, :3, :3].T + viewmats[b, :3, 3]  # camera coordinates in the COLMAP frame
        v = np.asarray(moved.world_to_camera[b], np.float64)
        x_moved = normalized @ v[:3, :3].T + v[:3, 3]
        np.testing.assert_allclose(x_moved, WORLD.scale * x, atol=2e-5)  # same direction, lengths × scale
        np.testing.assert_allclose(center_of(v), WORLD.to_normalized(center_of(viewmats[b])), atol=1e-5)


def blender_c2w(seed):
    rng = np.random.default_rng(seed)
    c2w = np.eye(4)
    c2w[:3, :3] = random_rotation(seed + 100)
    c2w[:3, 3] = rng.normal(size=3)
    return c2w


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_from_blender_is_opengl_conversion_then_from_colmap(seed):
    c2w = blender_c2w(seed)
    K = cams.pinhole_K(W, H, 60.0)
    camera = cams.from_blender(WORLD, c2w, K, W, H)
    viewmat = opengl_c2w_to_viewmat(c2w.tolist(), "frames[0]", pathlib.Path("transforms.json"))
    expected = cams.from_colmap(WORLD, viewmat, K, W, H)
    np.testing.assert_allclose(np.asarray(camera.world_to_camera), np.asarray(expected.world_to_camera), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(camera.K), np.asarray(expected.K))
    # a point straight ahead of the Blender camera (its -z axis, OpenGL) is at the image centre, in front
    ahead = c2w[:3, 3] - 2.0 * c2w[:3, 2]
    pixel, depth = project(camera, WORLD.to_normalized(ahead))
    np.testing.assert_allclose(pixel, [W / 2, H / 2], atol=1e-3)
    assert depth == pytest.approx(2.0 * WORLD.scale, rel=1e-5)
    # and a point above it (its +y axis, OpenGL's up) is above the image centre
    above, _ = project(camera, WORLD.to_normalized(ahead + 0.1 * c2w[:3, 1]))
    assert above[1] < H / 2 and above[0] == pytest.approx(W / 2, abs=1e-3)
    c2w_before = c2w.copy()
    cams.from_blender(WORLD, c2w, K, W, H)
    np.testing.assert_array_equal(c2w, c2w_before)  # the caller's matrix is not modified
