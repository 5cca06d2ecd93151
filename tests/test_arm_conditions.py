"""The arm scene's physical imaging conditions (issue 20), rendered by SAPIEN: a directional light whose intensity
dims, an occluding plate moved into view, as the robustness matrix on the arm configures them
(`orchestration.experiment_robustness_arm`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orchestration.arm_run import SCENE
from orchestration.experiment_robustness import DT
from orchestration.experiment_robustness_arm import OCCLUDED_SHARE, OCCLUDER_FRAMES, arm_scene, shipped_template
from sim.arm import ArmSim
from sim.arm_scene import scene_config_from_dict


def _at_reference(condition: str) -> ArmSim:
    config, _ = arm_scene(condition, "paper")
    assert config.start is not None
    sim = ArmSim(config)
    sim.place_camera(config.start.T_target_ref, config.start.target)
    return sim


def _render_at(sim: ArmSim, t: float) -> np.ndarray:
    sim.time = t  # the scene's scripts follow the simulated clock; the arm stays at the reference pose
    return sim.render().astype(np.float64)


def _template_box(sim: ArmSim) -> tuple[slice, slice]:
    k, (w, h) = sim.intrinsics, shipped_template()
    x0, y0 = round(k.cx - w / 2 + 0.5), round(k.cy - h / 2 + 0.5)
    return slice(y0, y0 + h), slice(x0, x0 + w)


def test_the_dimming_light_darkens_the_frame_to_a_third_over_ten_seconds() -> None:
    unlit = _render_at(_at_reference("nominal"), 0.0)
    lit = _at_reference("dimming_3x")
    full, half, end, later = (_render_at(lit, t) for t in (0.0, 5.0, 10.0, 20.0))
    # At full intensity the lit scene shows the texture's grey levels, as the unlit (ambient) scene does.
    assert np.abs(full - unlit).mean() < 0.6 and np.abs(full - unlit).max() <= 2.0
    bright = unlit > 30.0
    for image, gain in ((half, 2.0 / 3.0), (end, 1.0 / 3.0), (later, 1.0 / 3.0)):
        assert np.median(image[bright] / full[bright]) == pytest.approx(gain, abs=0.01)
    assert np.corrcoef(end.ravel(), unlit.ravel())[0, 1] > 0.999  # a global dimming: same picture, darker


def test_the_occluding_plate_enters_and_covers_its_share_of_the_template() -> None:
    clear = _render_at(_at_reference("nominal"), 0.0)
    sim = _at_reference("occluder_stays")
    t_start, t_end = (k * DT for k in OCCLUDER_FRAMES)
    rows, cols = _template_box(sim)
    times = (t_start - DT, t_start + 0.98 * (t_end - t_start), t_end + 1.0)
    before, entering, inside = (_render_at(sim, t) for t in times)
    np.testing.assert_array_equal(before, clear)  # out of view before it enters
    changed = np.abs(inside - clear) > 3.0
    share = changed[rows, cols].mean()
    assert share == pytest.approx(OCCLUDED_SHARE, abs=0.03)
    covered_cols = np.flatnonzero(changed[rows, cols].mean(axis=0) > 0.5)
    edge = OCCLUDED_SHARE * shipped_template()[0] - 1
    assert covered_cols.min() == 0 and covered_cols.max() == pytest.approx(edge, abs=1)
    assert changed[:, : cols.start].mean() > 0.9  # a plate, covering the image left of the template too
    assert 0.0 < (np.abs(entering - clear) > 3.0)[rows, cols].mean() < share  # on its way in


def test_scene_keys_for_light_and_occluders_are_parsed_and_checked() -> None:
    base = json.loads(SCENE.read_text())
    config = scene_config_from_dict({**base, "light": {"direction": [0, 0, -2]},
                                     "occluders": [{"width": 0.2, "height": 0.1, "t_start": 1.0, "t_end": 2.0,
                                                    "pose": {"t": [0.1, 0, -0.1]}, "offset": [-0.4, 0, 0]}]})
    assert config.light is not None and config.light.direction == (0.0, 0.0, -1.0)
    assert config.light.intensity(100.0) == 1.0
    plate = config.occluders[0]
    np.testing.assert_allclose(plate.T_target_plate_at(0.0)[:3, 3], [-0.3, 0.0, -0.1])
    np.testing.assert_allclose(plate.T_target_plate_at(1.5)[:3, 3], [-0.1, 0.0, -0.1])
    np.testing.assert_allclose(plate.T_target_plate_at(9.0)[:3, 3], [0.1, 0.0, -0.1])
    with pytest.raises(ValueError, match="light direction"):
        scene_config_from_dict({**base, "light": {"direction": [0, 0, 0]}})
    with pytest.raises(ValueError, match="t_end"):
        scene_config_from_dict({**base, "occluders": [{"width": 0.2, "height": 0.1, "t_start": 2.0, "t_end": 1.0}]})
    with pytest.raises(ValueError, match="offset must be 3 numbers"):
        scene_config_from_dict({**base, "occluders": [{"width": 0.2, "height": 0.1, "t_start": 0.0, "t_end": 1.0,
                                                       "offset": [0.1, 0.2]}]})
    with pytest.raises(ValueError, match="occluder target index"):
        ArmSim(scene_config_from_dict({**base, "occluders": [{"width": 0.2, "height": 0.1, "t_start": 0.0,
                                                               "t_end": 1.0, "target": 3}]}))


def test_a_short_arm_run_reports_its_measures() -> None:
    from orchestration.experiment_robustness import RobustnessSettings
    from orchestration.experiment_robustness_arm import run_arm_one

    run = run_arm_one("planar", "ddvs", "paper", "focal_x1.3", RobustnessSettings(max_images=8))
    assert run.outcome == "budget" and run.images == 8 and len(run.pose_errors_mm) == 8
    assert run.translation_error_mm > 200.0  # it has only started: 276 mm at the paper's start
    assert run.pose_errors_mm[-1] < run.pose_errors_mm[0]  # and it moves towards the goal
    with pytest.raises(ValueError, match=r"the arm runs the planar target"):
        run_arm_one("planar", "ddvs", "paper", "specular", RobustnessSettings(max_images=8))


def test_the_graf_scene_is_the_shipped_poster_with_the_free_flyers_texture() -> None:
    from orchestration.arm_run import ROOT
    from sim.textures import load_texture

    config, _ = arm_scene("nominal", "paper", ROOT / "configs" / "arm" / "ur5_poster_graf.json")
    shipped, _ = arm_scene("nominal", "paper")
    assert config.targets[0].T_world_target.tolist() == shipped.targets[0].T_world_target.tolist()
    np.testing.assert_array_equal(config.targets[0].texture_image(), load_texture("graf").astype(np.uint8))
