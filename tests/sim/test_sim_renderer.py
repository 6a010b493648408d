"""The EGL renderer: hand-computed boxes, behind-camera and occluded buildings, depth, pitch, errors."""

import math

import numpy as np
import pytest

from openfly_agent.sim import renderer as R
from openfly_agent.sim.camera import CameraModel, camera_axes, project
from openfly_agent.sim.city import CityConfig, generate_city
from openfly_agent.sim.instance_boxes import instance_boxes
from openfly_agent.utils.geometry import Pose

from .scenes import TOWER_HI, TOWER_LO, assert_same_frame, pixel_box, tower_city, west_face

CAM = CameraModel(224, 224, 90.0)
EYE = Pose(0.0, 0.0, 50.0, 0.0)  # 50 m up, looking east at the tower
ONE_PX = 1.0 / 224


@pytest.fixture(scope="module")
def renderer():
    r = R.CityRenderer(224, 224, 90.0, min_box_pixels=1)
    yield r
    r.close()


def test_projection_of_a_point_ahead_is_hand_computed():
    uv, depth = project(np.array([[90.0, -10.0, 100.0]]), EYE, 0.0, CAM)
    # focal = 112 px; right of the heading is -y; up is +z
    np.testing.assert_allclose(uv[0], [112 + 112 * 10 / 90, 112 - 112 * 50 / 90])
    assert depth[0] == pytest.approx(90.0)


def test_tower_straight_ahead_is_centred_with_the_hand_computed_box(renderer):
    out = renderer.render(tower_city(), EYE, 0.0, ids=True)
    assert set(out.boxes) == {"b0000"}
    expected = pixel_box(west_face(TOWER_LO, TOWER_HI), EYE, CAM)
    # columns 100..123 and rows 50..173: cx = cy = 0.5, w = 24 px, h = 124 px
    np.testing.assert_allclose(expected, [0.5, 0.5, 24 / 224, 124 / 224])
    np.testing.assert_allclose(out.boxes["b0000"], expected, atol=ONE_PX + 1e-9)
    assert out.pixel_counts["b0000"] == pytest.approx(24 * 124, rel=0.03)
    red = out.rgb[112, 112].astype(int)
    assert red[0] > red[1] + 40 and red[0] > red[2] + 40  # the red facade, not sky or ground
    assert (out.instance_ids[112, 112], out.instance_ids[10, 10]) == (1, 0)


def test_no_box_for_a_building_behind_the_camera(renderer):
    out = renderer.render(tower_city(((-110.0, -10.0, 0.0), (-90.0, 10.0, 100.0))), EYE, 0.0)
    assert set(out.boxes) == {"b0000"}
    turned = renderer.render(
        tower_city(((-110.0, -10.0, 0.0), (-90.0, 10.0, 100.0))), Pose(0, 0, 50, math.pi)
    )
    assert set(turned.boxes) == {"b0001"}
    np.testing.assert_allclose(turned.boxes["b0001"], [0.5, 0.5, 24 / 224, 124 / 224], atol=ONE_PX + 1e-9)


def test_occlusion_cuts_the_box_and_hides_buildings_completely(renderer):
    front = ((40.0, -5.0, 0.0), (50.0, 5.0, 30.0))  # low block in front: hides the tower below row 168
    hidden = ((150.0, -5.0, 0.0), (160.0, 5.0, 50.0))  # behind the tower, entirely inside its silhouette
    out = renderer.render(tower_city(front, hidden), EYE, 0.0)
    assert "b0002" not in out.boxes
    # The block's roof is a trapezoid: front edge v = 112 + 112 * 20 / 40 = 168 (u 98..126), back edge
    # v = 112 + 112 * 20 / 50 = 156.8 (u 100.8..123.2). In the tower's outer column 100 (centre u = 100.5)
    # the roof's slanted side is at v = 168 - 11.2 * 2.5 / 2.8 = 158, so the tower shows down to row 157.
    np.testing.assert_allclose(
        out.boxes["b0000"], [0.5, (50 + 157 + 1) / 2 / 224, 24 / 224, 108 / 224], atol=ONE_PX
    )
    assert out.pixel_counts["b0000"] < 24 * 108
    # the block itself: columns of its front face (u 98..126 -> 98..125), rows from its roof's back edge
    # (row 157) down to the image bottom (its base would be at v = 112 + 112 * 50 / 40 = 252)
    np.testing.assert_allclose(
        out.boxes["b0001"], [0.5, (157 + 223 + 1) / 2 / 224, 28 / 224, 67 / 224], atol=ONE_PX
    )


def _ground_depth(row: int, col: int, height: float, pitch_deg: float) -> float:
    """Depth along the view axis where pixel (row, col)'s centre ray meets flat ground `height` below."""
    forward, right, up = camera_axes(0.0, pitch_deg)
    ray = forward + (col + 0.5 - 112) / 112 * right - (row + 0.5 - 112) / 112 * up  # forward component 1
    return height / -ray[2]


def test_depth_is_metric_along_the_view_axis(renderer):
    out = renderer.render(tower_city(), EYE, 0.0, depth=True)
    assert out.depth[112, 112] == pytest.approx(90.0, rel=1e-3)  # the tower's west face
    assert _ground_depth(200, 5, 50.0, 0.0) == pytest.approx(50 * 112 / (200.5 - 112))
    assert out.depth[200, 5] == pytest.approx(_ground_depth(200, 5, 50.0, 0.0), rel=1e-3)  # flat ground
    assert np.isinf(out.depth[100, 5])  # sky


def test_pitch_minus_45_moves_the_horizon_to_the_top(renderer):
    city = tower_city()
    away = Pose(0.0, 0.0, 50.0, math.pi / 2)  # looking north, nothing but ground and sky
    level = renderer.render(city, away, 0.0, depth=True)
    down = renderer.render(city, away, -45.0, depth=True)
    sky_rows_level = np.isinf(level.depth).all(axis=1).sum()
    sky_rows_down = np.isinf(down.depth).all(axis=1).sum()
    assert sky_rows_level == 113  # rows 0..112: row 112 sees the ground beyond the 4 km far plane
    assert sky_rows_down <= 3  # tan(45 deg) * focal = 112 px: the horizon sits at the top edge
    # near the image centre at -45 deg the ray meets the ground ~50 m ahead, ~50 * sqrt(2) m along the axis
    assert _ground_depth(112, 112, 50.0, -45.0) == pytest.approx(50 * math.sqrt(2), rel=1e-2)
    for row, col in ((112, 112), (200, 30), (20, 200)):
        assert down.depth[row, col] == pytest.approx(_ground_depth(row, col, 50.0, -45.0), rel=1e-3)


def test_generated_city_frame_is_textured_and_has_boxes(renderer):
    city = generate_city(2, CityConfig(size_m=300.0, n_buildings=30, n_trees=40))
    out = renderer.render(city, Pose(-160.0, -160.0, 60.0, math.pi / 4), -20.0, ids=True)
    assert out.rgb.std() > 20 and len(np.unique(out.rgb.reshape(-1, 3), axis=0)) > 500
    assert len(out.boxes) >= 5
    ids, boxes, counts = instance_boxes(out.instance_ids, len(city.buildings), renderer.min_box_pixels)
    assert [city.buildings[k - 1].landmark_id for k in ids] == list(out.boxes)
    np.testing.assert_array_equal(np.stack(list(out.boxes.values())), boxes)


def test_missing_egl_fails_with_what_to_install(monkeypatch):
    import moderngl

    def broken(*args, **kwargs):
        raise Exception("eglGetDisplay failed")

    monkeypatch.setattr(moderngl, "create_standalone_context", broken)
    with pytest.raises(RuntimeError, match="apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"):
        R.CityRenderer(32, 32).render(tower_city(), EYE)


def test_a_batch_renders_what_single_frames_render(renderer):
    city = generate_city(2, CityConfig(size_m=300.0, n_buildings=30, n_trees=40))
    rng = np.random.default_rng(0)
    poses = [Pose(*rng.uniform(-140, 140, 2), rng.uniform(10, 80), rng.uniform(-3, 3)) for _ in range(18)]
    pitches = [0.0 if k % 3 else -45.0 for k in range(18)]  # 18 views: a full batch of 16, then 2
    batch = renderer.render_batch(city, poses, pitches, depth=True, ids=True)
    assert len(batch) == 18
    for pose, pitch, out in zip(poses, pitches, batch):
        single = renderer.render(city, pose, pitch, depth=True, ids=True)
        assert_same_frame(out, single)
        assert np.mean(out.instance_ids != single.instance_ids) <= 0.005
        finite = np.isfinite(single.depth) & np.isfinite(out.depth)
        assert finite.mean() > 0.3
        np.testing.assert_allclose(out.depth[finite], single.depth[finite], rtol=2e-3)
        for key, count in single.pixel_counts.items():
            assert abs(out.pixel_counts[key] - count) <= max(3, 0.02 * count)
    assert not np.array_equal(batch[0].rgb, batch[1].rgb)
    again = renderer.render_batch(city, poses, pitches)  # same slots: bit-identical
    for first, second in zip(batch, again):
        np.testing.assert_array_equal(first.rgb, second.rgb)


def test_an_invalid_instance_read_back_is_drawn_again_once(renderer, monkeypatch):
    from openfly_agent.sim.instance_boxes import InstanceIdError

    city = tower_city()
    expected = renderer.render(city, EYE, 0.0)
    real, failures = renderer._read_back, []

    def flaky(*args, **kwargs):
        if len(failures) < budget[0]:
            failures.append(1)
            raise InstanceIdError("instance ids must lie in [0, 1], got [-2147483648, 5]")
        return real(*args, **kwargs)

    budget = [1]
    monkeypatch.setattr(renderer, "_read_back", flaky)
    again = renderer.render(city, EYE, 0.0)
    assert failures == [1] and again.boxes.keys() == expected.boxes.keys()
    np.testing.assert_array_equal(again.rgb, expected.rgb)
    failures.clear()
    budget[0] = 2  # fails twice in a row: the error reaches the caller
    with pytest.raises(InstanceIdError):
        renderer.render(city, EYE, 0.0)
