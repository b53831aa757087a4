"""The generated parameter panel, alone: widgets from ParamInfo, validation, presets, log."""

from __future__ import annotations

from pathlib import Path

import pytest
from hapticloud.app.param_panel import (
    BoolEditor,
    ChoiceEditor,
    NumberEditor,
    ParamPanel,
    RangeEditor,
    ScientificEditor,
    pretty_name,
    slider_span,
)
from hapticloud.core.fusion import FusionConfig
from hapticloud.hardware.live.contract import LiveConfig

pytestmark = pytest.mark.usefixtures("qapp")


@pytest.fixture
def panel(qtbot) -> ParamPanel:
    widget = ParamPanel(LiveConfig())
    qtbot.addWidget(widget)
    return widget


def test_every_parameter_has_a_widget_of_its_kind(panel: ParamPanel) -> None:
    infos = {info.path: info for info in LiveConfig.params()}
    assert set(panel.paths()) == set(infos)
    for path, info in infos.items():
        editor = panel.editor(path)
        if info.name in ("r_in_m", "r_out_m"):
            assert isinstance(editor, RangeEditor)
        elif info.kind is bool:
            assert isinstance(editor, BoolEditor)
        elif info.choices:
            assert isinstance(editor, ChoiceEditor)
            assert [editor.combo.itemText(i) for i in range(editor.combo.count())] == list(
                info.choices
            )
        elif info.kind is float and 0 < abs(info.default) < 1e-6:
            # Solver tolerances: typed, shown exactly (a spin box would read 0).
            assert isinstance(editor, ScientificEditor)
            assert editor.value() == info.default
        else:
            assert isinstance(editor, NumberEditor)
            if info.unit:
                assert editor.spin.suffix() == f" {info.unit}"
        assert info.doc in editor.toolTip()
    # Both tables are there, as tabs.
    tabs = [panel.tabs.tabText(i) for i in range(panel.tabs.count())]
    assert tabs == ["Perception", "Fusion / PID", "Haptics", "Controller"]


def test_widgets_show_the_defaults(panel: ParamPanel) -> None:
    for path in panel.paths():
        editor = panel.editor(path)
        value = LiveConfig().get_path(path)
        if isinstance(editor, RangeEditor):
            pair = [p for p in panel.paths() if panel.editor(p) is editor]
            assert editor.value() == pytest.approx(tuple(LiveConfig().get_path(p) for p in pair))
        else:
            assert (
                editor.value() == pytest.approx(value)
                if isinstance(value, float)
                else (editor.value() == value)
            )


def test_log_scale_and_wide_ranges_get_log_sliders() -> None:
    infos = {info.path: info for info in LiveConfig.params()}
    voxel = slider_span(infos["perception.voxel.voxel_size_m"])
    assert voxel is not None and voxel.log
    assert voxel.lo <= 0.0035 <= voxel.hi
    points = slider_span(infos["perception.reconstruction.icp_max_points"])  # 10..1e5
    assert points is not None and points.log
    ki = slider_span(infos["fusion.ki"])  # 0..1e8 at 0: no span says anything; spin box only
    assert ki is None
    n_shells = slider_span(infos["perception.abstraction.n_shells"])
    assert n_shells is not None and not n_shells.log and (n_shells.lo, n_shells.hi) == (1, 50)
    assert pretty_name("voxel_size_m") == "voxel size"
    assert pretty_name("max_speed_m_s") == "max speed"


def test_slider_change_is_validated_applied_and_logged(panel: ParamPanel, qtbot) -> None:
    editor = panel.editor("perception.voxel.voxel_size_m")
    assert isinstance(editor, NumberEditor) and editor.slider is not None
    with qtbot.waitSignal(panel.config_changed) as emitted:
        editor.slider.setValue(editor.span.to_slider(0.005))  # a click on the groove
    new = emitted.args[0]
    assert new.perception.voxel.voxel_size_m == pytest.approx(0.005, rel=0.01)
    assert panel.config is new
    assert editor.spin.value() == pytest.approx(new.perception.voxel.voxel_size_m)
    top = panel.change_log.topLevelItem(0)
    assert top.text(1) == "voxel.voxel_size_m"
    assert top.toolTip(1) == "perception.voxel.voxel_size_m"
    assert "0.0035 m →" in top.text(2)


def test_invalid_value_is_refused_reverted_and_explained(panel: ParamPanel, qtbot) -> None:
    editor = panel.editor("perception.crop.workspace_radius_m")
    applied: list[object] = []
    panel.config_changed.connect(applied.append)
    with qtbot.waitSignal(panel.refused) as refusal:
        editor.spin.setValue(0.05)  # the shells reach 0.15 m: beyond the workspace
    reason = refusal.args[0]
    assert "must not exceed crop.workspace_radius_m" in reason
    assert applied == []
    assert panel.config == LiveConfig()
    assert editor.value() == pytest.approx(0.15)  # reverted to the value in effect
    assert panel.error_label.isVisibleTo(panel) and reason in panel.error_label.text()
    assert "refused" in panel.change_log.topLevelItem(0).text(2)


def test_unstable_gains_are_refused_with_the_reason(panel: ParamPanel) -> None:
    assert not panel.set_value("fusion.ki", 2.0 * panel.config.fusion.kp * panel.config.fusion.kd)
    assert "Routh-Hurwitz" in panel.error_label.text()
    assert panel.config.fusion.ki == 0.0
    assert panel.set_value("fusion.ki", 1000.0)
    assert not panel.error_label.isVisibleTo(panel)


def test_range_pair_moves_both_ends_in_a_valid_order(panel: ParamPanel) -> None:
    editor = panel.editor("perception.reconstruction.r_in_m")
    assert isinstance(editor, RangeEditor)
    # Both move up past the old outer radius: r_out must move first, the panel finds the order.
    editor.slider.setValue((0.08, 0.1))
    rec = panel.config.perception.reconstruction
    assert (rec.r_in_m, rec.r_out_m) == pytest.approx((0.08, 0.1))


def test_presets_round_trip_and_bad_presets_are_refused(panel: ParamPanel, tmp_path: Path) -> None:
    assert panel.set_value("perception.abstraction.method", "paper")
    assert panel.set_value("perception.cluster.min_cluster_points", 35)
    assert panel.set_value("fusion.kp", 1600.0)
    assert panel.set_value("perception.reconstruction.enabled", False)
    tuned = panel.config
    path = tmp_path / "tuned.toml"
    panel.save_preset(path)
    panel.reset_defaults()
    assert panel.config == LiveConfig()
    assert panel.editor("fusion.kp").value() == pytest.approx(FusionConfig().kp)
    assert panel.load_preset(path)
    assert panel.config == tuned
    assert panel.editor("perception.abstraction.method").value() == "paper"
    assert panel.editor("perception.reconstruction.enabled").value() is False
    bad = tmp_path / "bad.toml"
    bad.write_text("[perception.voxel]\nvoxel_size = 0.01\n")
    assert not panel.load_preset(bad)
    assert "unknown key" in panel.error_label.text()
    assert panel.config == tuned  # nothing applied
    log = [panel.change_log.topLevelItem(i).text(1) for i in range(4)]
    assert log[0] == "preset refused" and log[1] == "preset tuned.toml"
