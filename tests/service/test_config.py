"""Settings layering: defaults < file < environment < flags."""

from __future__ import annotations

import json

import pytest

from pd_service.errors import ConfigError
from pd_service.service.__main__ import main, settings_from_args
from pd_service.service.config import load_settings
from pd_service.transport.options import DAEMON, DEFAULT_ENDPOINT


def test_layers_flags_over_env_over_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('instance = "from-file"\nexpire_s = 30\nconnect = ["tcp/1.1.1.1:7447"]\n'
                 'batch_budget = 4\n')
    env = {"PD_SERVICE_EXPIRE_S": "45", "PD_SERVICE_CONNECT": "tcp/2.2.2.2:7447, tcp/3.3.3.3:1",
           "PD_SERVICE_MULTICAST": "true"}
    s = load_settings({"expire_s": 60.0, "instance": None}, environ=env, config_file=f)
    assert s.instance == "from-file"  # file (flag was not given)
    assert s.expire_s == 60.0  # flag beats env beats file
    assert s.connect == ["tcp/2.2.2.2:7447", "tcp/3.3.3.3:1"]  # env beats file
    assert s.batch_budget == 4 and s.multicast is True
    assert s.zenoh.resolved(DAEMON).listen == (DEFAULT_ENDPOINT,)


def test_a_client_daemon_listens_on_nothing_unless_told():
    """The daemon's listen default is a peer's: made a client of a router it binds no port
    (two such instances on one host would both take 7447), unless given endpoints."""
    assert load_settings({"mode": "client"}, environ={}).zenoh.resolved(DAEMON).listen == ()
    assert load_settings({"mode": "client", "listen": ["tcp/127.0.0.1:7500"]},
                         environ={}).zenoh.resolved(DAEMON).listen == ("tcp/127.0.0.1:7500",)
    assert load_settings({"mode": "peer"}, environ={}).zenoh.resolved(DAEMON).listen == \
        (DEFAULT_ENDPOINT,)


def test_json_file_and_config_env_var(tmp_path):
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"shard": "1/3", "zenoh_config": "/etc/z.json5"}))
    s = load_settings({}, environ={"PD_SERVICE_CONFIG": str(f)})
    assert s.shard_tuple == (1, 3)
    assert s.zenoh.resolved(DAEMON).listen == ()  # a zenoh config file decides the endpoints


@pytest.mark.parametrize("flags, env, match", [
    ({"shard": "2/2"}, {}, "shard"),
    ({"instance": "Bad Name"}, {}, "instance"),
    ({}, {"PD_SERVICE_EXPIRE_S": "soon"}, "expire_s"),
    ({}, {"PD_SERVICE_TICK_PHASE": "1.5"}, "tick_phase"),
    ({"expire_s": -1.0}, {}, "expire_s .flags."),
])
def test_bad_values_name_the_field(flags, env, match):
    with pytest.raises(ConfigError, match=match):
        load_settings(flags, environ=env)


def test_expire_s_zero_means_never_and_is_accepted():
    assert load_settings({}, environ={"PD_SERVICE_EXPIRE_S": "0"}).expire_s == 0.0


def test_unknown_setting_in_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text("expire = 3\n")
    with pytest.raises(ConfigError, match="unknown setting 'expire'"):
        load_settings({}, environ={}, config_file=f)


def test_cli_flags(monkeypatch, capsys):
    monkeypatch.delenv("PD_SERVICE_CONFIG", raising=False)
    s, show = settings_from_args(["--instance", "x", "--connect", "tcp/a:1", "--connect",
                                  "tcp/b:2", "--listen", "tcp/127.0.0.1:9000", "--shard", "0/2"])
    assert (s.instance, s.connect, list(s.zenoh.resolved(DAEMON).listen), s.shard) == \
        ("x", ["tcp/a:1", "tcp/b:2"], ["tcp/127.0.0.1:9000"], "0/2")
    assert main(["--print-config", "--instance", "y"]) == 0
    assert json.loads(capsys.readouterr().out)["instance"] == "y"
    assert main(["--shard", "nonsense", "--print-config"]) == 2


def test_print_config_shows_the_zenoh_values_in_force(monkeypatch, capsys, tmp_path):
    for var in ("PD_SERVICE_CONFIG", "PD_SERVICE_MODE", "PD_SERVICE_LISTEN",
                "PD_SERVICE_CONNECT", "PD_SERVICE_MULTICAST", "PD_SERVICE_ZENOH_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    assert main(["--print-config", "--instance", "y", "--state-dir", str(tmp_path)]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert (shown["mode"], shown["listen"], shown["connect"], shown["multicast"]) == \
        ("peer", [DEFAULT_ENDPOINT], [], False)
    assert shown["state_dir"] == str(tmp_path)
    assert main(["--print-config", "--mode", "client", "--connect", "tcp/127.0.0.1:9",
                 "--password", "secret"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert (shown["mode"], shown["listen"], shown["connect"], shown["password"]) == \
        ("client", [], ["tcp/127.0.0.1:9"], "***")  # a client listens on nothing
    # with a zenoh config file, the file decides what the flags do not say
    f = tmp_path / "z.json5"
    f.write_text('{mode: "client"}')
    assert main(["--print-config", "--zenoh-config", str(f)]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert (shown["mode"], shown["listen"]) == (None, None)


def test_unknown_environment_setting_is_refused_by_name():
    # a misspelt or retired PD_SERVICE_ variable is refused, never silently ignored
    with pytest.raises(ConfigError, match="unknown setting 'PD_SERVICE_LATENCY_WINDW'"):
        load_settings(environ={"PD_SERVICE_LATENCY_WINDW": "100"})
    # the prefix's non-settings (config file, pure switch, profile) are not settings
    s = load_settings(environ={"PD_SERVICE_PURE": "1", "PD_SERVICE_PROFILE": "/tmp/x.prof",
                               "PD_SERVICE_LATENCY_WINDOW": "100"})
    assert s.latency_window == 100
