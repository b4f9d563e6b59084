"""pd-demo's link configuration ships with the package (deploy/link-paper.toml is the same file)."""

from __future__ import annotations

from pathlib import Path

from pd_client.tools.pd_demo import main, packaged_link_config
from pd_service.link.config import load_config

DEPLOY_LINK = Path(__file__).resolve().parents[3] / "deploy" / "link-paper.toml"


def test_the_packaged_link_config_is_the_papers_link():
    with packaged_link_config() as path:
        assert path.is_file()
        cfg = load_config(path)
        assert path.read_bytes() == DEPLOY_LINK.read_bytes()
    assert cfg.step_ms == 50
    assert {r.name for r in cfg.downlink} >= {"camera", "ranger"}


def test_a_missing_link_config_exits_2(tmp_path, capsys):
    assert main(["--link-config", str(tmp_path / "nope.toml"), "--out", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err


def test_the_async_demo_link_passes_the_sensors_and_delays_the_commands_by_the_lead():
    from pd_service.scenarios import get_scenario

    with packaged_link_config("link-async.toml") as path:
        cfg = load_config(path)
        assert path.read_bytes() == DEPLOY_LINK.with_name("link-async.toml").read_bytes()
    sc = get_scenario("async")
    assert cfg.step_ms == sc.period_s * 1e3
    assert [r.name for r in cfg.downlink] == ["sensors"] and [r.name for r in cfg.uplink] == [
        "commands"]


def test_ros2_and_async_together_exit_2(tmp_path, capsys):
    assert main(["--ros2", "--async", "--out", str(tmp_path)]) == 2
    assert "choose one" in capsys.readouterr().err
