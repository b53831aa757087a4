"""The trade study's pure parts: knobs and their ranges, trials, the front, presets, one trial's
measurement and the extremes' check."""

from __future__ import annotations

import math
import tomllib

import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.core.scene import SceneConfig
from hapticloud.core.studies.trade import front as fr
from hapticloud.core.studies.trade import knobs as k
from hapticloud.core.studies.trade.evaluate import OBJECTIVES, TrialResult, TrialSpec, evaluate


def _trial(lat: float, err: float, unsafe: bool = False, **params: float) -> TrialResult:
    objectives = dict.fromkeys(OBJECTIVES, math.nan)
    objectives.update(
        latency_ms_median=lat, centroid_mm_p90=err, centroid_mm_median=0.2, d_proj_mm_p90=1.0
    )
    return TrialResult(params, objectives, unsafe, ("why",) if unsafe else ())


def test_a_grid_is_the_full_product_with_values_checked() -> None:
    grids = [
        k.parse_grid("perception.voxel.voxel_size_m=0.0025, 0.005"),
        k.parse_grid("perception.abstraction.quadric.bandwidth_m=0.02,0.035,0.05"),
    ]
    trials = k.grid_trials(grids)
    assert len(trials) == k.grid_size(grids) == 6
    assert {
        "perception.voxel.voxel_size_m": 0.005,
        "perception.abstraction.quadric.bandwidth_m": 0.05,
    } in trials
    assert k.parse_grid("perception.cluster.keep=largest,nearest_to_hip")[1] == [
        "largest",
        "nearest_to_hip",
    ]


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("perception.voxel.size=0.004", "unknown knob"),
        ("scene.seed=1,2", "unknown knob"),
        ("perception.voxel.voxel_size_m=0.0001", "must be in [0.0005, 0.05]"),
        ("perception.voxel.voxel_size_m=", "empty grid"),
        ("perception.cluster.keep=biggest", "must be one of"),
    ],
)
def test_bad_grids_are_refused_naming_the_knob(text: str, needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        k.parse_grid(text)
    assert needle in str(err.value)


def test_space_ranges_are_numeric_and_ordered() -> None:
    r = k.parse_space("perception.voxel.voxel_size_m=0.002:0.008:log")
    assert (r.lo, r.hi, r.log, r.integer) == (0.002, 0.008, True, False)
    assert k.parse_space("perception.reconstruction.icp_max_iterations=5:30").integer
    for bad in ("perception.voxel.voxel_size_m=0.008:0.002", "perception.cluster.keep=a:b"):
        with pytest.raises(ConfigError):
            k.parse_space(bad)


def test_companions_keep_a_trial_inside_the_cross_field_rules() -> None:
    params = {"perception.abstraction.r_out_m": 0.2, "perception.voxel.voxel_size_m": 0.02}
    cfg = k.trial_config(params)
    assert cfg.perception.crop.workspace_radius_m == 0.2
    assert cfg.perception.max_spacing_m == 0.02
    with pytest.raises(ConfigError):  # without them the config is refused
        SceneConfig().with_overrides(params)


def test_the_front_holds_exactly_the_non_dominated_safe_trials() -> None:
    trials = [
        _trial(1.0, 9.0),
        _trial(2.0, 4.0),
        _trial(3.0, 1.0),
        _trial(2.5, 5.0),  # dominated by (2, 4)
        _trial(0.5, 0.5, unsafe=True),  # would dominate all: never on the front
        _trial(4.0, math.nan),  # a missing figure: never on the front
    ]
    front = fr.pareto_front(trials)
    assert sorted(front) == [0, 1, 2]
    for i in front:
        assert not any(
            fr.dominates(
                (
                    trials[j].objectives["latency_ms_median"],
                    trials[j].objectives["centroid_mm_p90"],
                ),
                (
                    trials[i].objectives["latency_ms_median"],
                    trials[i].objectives["centroid_mm_p90"],
                ),
            )
            for j in front
        )


def test_presets_follow_their_documented_rules() -> None:
    trials = [_trial(1.0, 9.0), _trial(2.0, 4.0), _trial(2.4, 1.0), _trial(6.0, 0.5)]
    front = fr.pareto_front(trials)
    presets = fr.pick_presets(trials, front, default_index=1)
    assert presets["fast"] == 1  # the fastest meeting 5 mm p90
    assert presets["accurate"] == 2  # 6 ms is over 1.25 x the default's 2 ms
    assert presets["balanced"] in front


def test_a_preset_file_loads_as_a_partial_config() -> None:
    text = fr.preset_toml(
        {"perception.voxel.voxel_size_m": 0.005, "fusion.window_s": 0.3}, ["made by a test"]
    )
    assert text.startswith("# made by a test\n")
    cfg = SceneConfig.from_dict(tomllib.loads(text))
    assert cfg.perception.voxel.voxel_size_m == 0.005 and cfg.fusion.window_s == 0.3
    assert cfg.perception.crop == SceneConfig().perception.crop


def test_extreme_cases_cover_every_knob_bound_and_the_pairs() -> None:
    cases = dict(k.extreme_cases())
    keys = {key for params in cases.values() for key in params}
    numeric = [p for p in k.knob_infos().values() if p.kind in (int, float)]
    assert {p.path for p in numeric} <= keys
    assert any("r_in_m~perception.abstraction.r_out_m" in label for label in cases)


def test_one_trial_is_deterministic_but_for_its_latency() -> None:
    spec = TrialSpec({"perception.voxel.voxel_size_m": 0.005}, ("sphere_head",), 4)
    a, b = evaluate(spec), evaluate(spec)
    acc = [n for n in OBJECTIVES if not n.startswith("latency")]
    assert [a.objectives[n] for n in acc] == pytest.approx(
        [b.objectives[n] for n in acc], nan_ok=True, rel=0, abs=0
    )
    assert a.estimates == 4 and math.isfinite(a.objectives["centroid_mm_p90"])
    assert math.isfinite(a.objectives["latency_ms_median"]) and not a.unsafe


def test_a_refused_config_is_reported_not_raised() -> None:
    spec = TrialSpec({"perception.abstraction.r_in_m": 0.9}, ("sphere_head",), 2)
    result = evaluate(spec)
    assert result.unsafe and result.reasons[0].startswith("refused: ")


@pytest.mark.parametrize(
    "label",
    [
        "perception.voxel.voxel_size_m=0.0005",
        "perception.voxel.voxel_size_m=0.05",
        "perception.abstraction.quadric.bandwidth_m=0.005",
        "perception.abstraction.quadric.robust=none",
        "perception.cluster.min_cluster_points=1000000",
        # The margin swallowed the surface next to the HIP: 30.6 mm farther at frame 3.
        "perception.crop.exclude_margin_m=0.1",
        "camera.decimation=16",
    ],
)
def test_extremes_subset_no_exception_no_nan_budget_or_reason(label: str) -> None:
    params = dict(k.extreme_cases())[label]
    spec = TrialSpec(params, ("sphere_head_occluded",), 6, companions=False)
    result = evaluate(spec, budget_mm=10.0)
    assert result.problems == ()
    if not result.reasons:
        assert all(
            math.isfinite(result.objectives[n]) for n in ("centroid_mm_p90", "latency_ms_p90")
        )


def test_camera_decimation_is_a_knob_of_the_frames() -> None:
    from hapticloud.core.studies.trade.evaluate import _frames, shipped_default

    assert k.parse_grid("camera.decimation=1,4")[1] == [1, 4]
    assert shipped_default("camera.decimation") == 1  # the benchmark camera's full resolution
    for bad in ("camera.decimation=0", "camera.decimation=17", "camera.decimation=2.5"):
        with pytest.raises(ConfigError, match=r"camera\.decimation"):
            k.parse_grid(bad)
    assert k.trial_config({"camera.decimation": 4}) == SceneConfig()  # not a scene parameter
    full, binned = _frames("sphere_head", 2, 7, 1), _frames("sphere_head", 2, 7, 4)
    assert binned[0].depth.depth_m.shape == (full[0].depth.depth_m.shape[0] // 4, 848 // 4)
    coarse = evaluate(TrialSpec({"camera.decimation": 4}, ("sphere_head",), 4))
    assert math.isfinite(coarse.objectives["centroid_mm_p90"]) and coarse.estimates == 4
    # 16x binned pixels are ~2.7 cm apart at the HIP: coarser than max_spacing_m, every estimate
    # invalid with its reason, the trial unsafe.
    blind = evaluate(TrialSpec({"camera.decimation": 16}, ("sphere_head",), 4))
    assert blind.unsafe and "no valid estimate" in blind.reasons and blind.problems == ()
