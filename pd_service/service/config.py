"""Daemon settings: defaults < file (TOML or JSON) < environment (``PD_SERVICE_*``) < flags.

Every field of :class:`Settings` can be set at each layer under the same name:

- file: ``--config FILE`` (or ``PD_SERVICE_CONFIG``); ``.toml`` is read as TOML, anything else
  as JSON; top-level keys are the field names (``expire_s = 900``);
- environment: ``PD_SERVICE_<FIELD>`` upper case (``PD_SERVICE_EXPIRE_S=900``); list fields
  (``listen``, ``connect``, ``peers``) are comma-separated;
- flags: ``--expire-s 900``, ``--connect EP`` (repeatable), see ``pd-service --help``.

A later layer replaces a field wholesale (a ``--connect`` flag replaces the file's list).
Bad values raise :class:`ConfigError` naming the field and the layer it came from.

The layers are pydantic-settings sources (:meth:`Settings.settings_customise_sources`): init
kwargs (flags) > :class:`EnvSettingsSource` > :class:`TomlConfigSettingsSource` /
:class:`JsonConfigSettingsSource`. They are used only inside :func:`load_settings`;
``Settings(**values)`` alone is defaults + ``values``, whatever the environment holds.
"""

from __future__ import annotations

import json
import os
import re
import socket
import tomllib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator
from pydantic.fields import FieldInfo
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    JsonConfigSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from pd_service.errors import ConfigError
from pd_service.transport.options import DEFAULT_ENDPOINT, PASSWORD_ENV, ZenohOptions
from pd_service.wire.keys import NAME_PATTERN

ENV_PREFIX = "PD_SERVICE_"
#: Variables with the prefix that are not settings: the config file's path, the switch to the
#: .py files (pd_service.native) and the worker's profile (daemon.py).
NOT_SETTINGS_ENV = frozenset({"PD_SERVICE_CONFIG", "PD_SERVICE_PURE", "PD_SERVICE_PROFILE"})
_SHARD_RE = re.compile(r"^(\d+)/(\d+)$")


def default_instance() -> str:
    """``pd-<hostname>`` reduced to the key-name alphabet ``[a-z0-9_-]`` (stable across restarts)."""
    host = re.sub(r"[^a-z0-9_-]+", "-", socket.gethostname().lower()).strip("-_") or "host"
    return ("pd-" + host)[:64]


def default_state_dir() -> Path:
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "pd-service"


class Settings(BaseSettings):
    """Everything the daemon can be told. Units are in the field names (``_s`` seconds)."""

    model_config = SettingsConfigDict(extra="forbid", validate_assignment=True)

    # identity and storage
    instance: str = Field(default_factory=default_instance,
                          description="Instance id (liveliness token, status key, ownership).")
    state_dir: Path | None = Field(None, description="Where session specs are persisted; "
                                   "default $XDG_STATE_HOME/pd-service/<instance>.")

    # zenoh
    mode: Literal["peer", "client", "router"] | None = Field(
        None, description="Zenoh mode; default peer (or the --zenoh-config file's).")
    listen: list[str] | None = Field(
        None, description=f"Zenoh listen endpoints; default [{DEFAULT_ENDPOINT}] "
                          "unless a zenoh config file is given.")
    connect: list[str] = Field(default_factory=list, description="Zenoh endpoints to connect to.")
    zenoh_config: Path | None = Field(None, description="Zenoh JSON5 config file, loaded first.")
    multicast: bool | None = Field(None, description="Multicast scouting; default off.")
    user: str | None = Field(None, description="Zenoh user (usrpwd authentication).")
    password: str | None = Field(None, description="Zenoh password (prefer the environment: "
                                "PD_SERVICE_PASSWORD, else PD_ZENOH_PASSWORD).")

    # operations
    metrics: str | None = Field(None, description="Address HOST:PORT of the Prometheus / "
                                "OpenMetrics endpoint (GET /metrics; port 0: any free port, "
                                "logged); none: no endpoint. Bind it to loopback or a private "
                                "network: it has no authentication")

    # scale-out
    shard: str | None = Field(None, description="Static sharding 'i/N': serve the sessions with "
                              "hash(session) % N == i. Default: rendezvous over live instances.")

    peers: list[str] = Field(default_factory=list, description="The other instances this one "
                             "shares sessions with (rendezvous, takeover, spec sync); empty: "
                             "standalone. Liveliness tokens of any other instance are ignored.")

    # sessions
    expire_s: float = Field(120.0, ge=0, description="Time without a measurement or command "
                            "after which a session expires (a spec's own expire_s wins); 0: "
                            "never.")
    idle_after_s: float = Field(5.0, gt=0, description="A session is idle (published only "
                                "every idle_publish_s instead of every step) until its first "
                                "measurement or command that decodes, and again after this "
                                "long without one.")
    idle_publish_s: float = Field(10.0, gt=0, description="An idle session gets one prediction "
                                  "per this period, at a step phase of its own.")
    min_period_ms: float = Field(1.0, gt=0, description="Specs with a shorter step period are "
                                 "refused (a 1 ns period would keep the worker busy).")
    max_sessions: int = Field(2_000, ge=1, description="Specs beyond this many are refused.")
    tick_phase: float = Field(0.5, ge=0.0, lt=1.0,
                              description="When in its step a session's tick fires (fraction "
                                          "of the period).")

    # admission (pd_service.service.admission): what a spec may cost
    max_session_bytes: int = Field(64 * 2**20, ge=2**20, description="Largest memory one "
                                   "session's tables and buffers may need (bytes).")
    max_session_cpu: float = Field(0.25, gt=0, description="Largest nominal CPU one session "
                                   "may need, fraction of a core (µs per step / period).")
    memory_budget_bytes: int = Field(256 * 2**20, ge=2**20, description="Memory all the "
                                     "sessions run here may need together (bytes; shared "
                                     "tables counted once).")
    cpu_budget: float = Field(0.8, gt=0, description="Nominal CPU all the sessions run here "
                              "may need together, fraction of a core (one worker thread).")
    tables_max_bytes: int = Field(64 * 2**20, ge=0, description="Bytes of shared propagation "
                                  "tables kept in the memo beyond the sessions using them.")

    max_abs_input: float = Field(1e12, gt=0, allow_inf_nan=False,
                                 description="Largest magnitude of a measured value or command "
                                             "entry accepted (out_of_range otherwise).")

    # work queues and limits
    inbox_size: int = Field(256, ge=1, description="Per-session inbox (messages); oldest dropped.")
    config_rate: float = Field(2.0, gt=0, description="Config changes (put or delete) per "
                               "second per session; more are refused (config_rate_limited).")
    config_burst: int = Field(5, ge=1, description="Config change burst per session.")
    config_rate_total: float = Field(20.0, gt=0, description="Config changes per second, all "
                                     "sessions together.")
    config_burst_total: int = Field(40, ge=1, description="Config change burst, all sessions.")
    config_slice: int = Field(2, ge=1, description="Config changes applied per worker round "
                              "(between two rounds of data and publications).")
    batch_budget: int = Field(16, ge=1, description="Messages of one session per round.")
    error_rate: float = Field(20.0, gt=0, description="ErrorReports per second per session.")
    error_burst: int = Field(20, ge=1, description="ErrorReport burst per session.")
    error_rate_total: float = Field(500.0, gt=0, description="ErrorReports per second, all "
                                    "sessions together (overload must not feed itself).")
    latency_window: int = Field(4096, ge=16, description="Latency samples kept service-wide for "
                                "the status' p50 / p99 (a benchmark sizes it to its interval).")
    sync_timeout_s: float = Field(1.0, gt=0, description="Wait for peers' specs at startup.")

    # restart and takeover (see pd_service.service.handover.keeper)
    checkpoint_interval_s: float = Field(
        1.0, ge=0, description="Least time between two checkpoints of one session in the "
                               "state directory (written when new steps were committed); 0: none.")
    replica_interval_s: float = Field(
        1.0, ge=0, description="Least time between two replicas of one session sent to its "
                               "successor instance (at most half the session's window: "
                               "max_delay steps); 0: none.")
    recover_samples: int = Field(
        256, ge=0, le=100_000, description="At start, and when a sender (re)appears, read back "
                                           "at most this many samples per cached sender key "
                                           "(sensors and commands) that it kept while no "
                                           "daemon received them; 0: none.")
    recover_timeout_s: float = Field(
        2.0, gt=0, description="Longest wait for the senders' caches (at start, and per "
                               "session at a takeover): once to find them (liveliness), once "
                               "for their answers (so up to twice this).")

    round_interval_us: float = Field(
        1000.0, ge=0, description="Least time between the starts of two worker loops while "
                                  "messages keep arriving, µs: what arrives meanwhile is "
                                  "handled as one batch (one prediction per session it "
                                  "touched). Adds at most this much to a message's wait; 0: "
                                  "no pause.")
    switch_interval_us: float = Field(
        200.0, gt=0, description="Python's GIL switch interval (sys.setswitchinterval), µs: "
                                 "how long a Zenoh callback may wait for the worker to yield "
                                 "the interpreter (Python's default is 5000).")

    # robot clocks (issue 43; pd_service.service.robot_time, clock_probes)
    probe_interval_s: float = Field(
        1.0, ge=0, description="Least time between two clock probes of one session whose spec "
                               "has robot_clock 'estimated' (a query of the robot's probe "
                               "queryable, from a thread of their own); 0: no probes.")
    probe_timeout_s: float = Field(
        0.5, gt=0, description="Longest wait for one probe's answer (a robot that does not "
                               "answer costs the probing thread this long, never the worker).")
    learned_window: bool = Field(
        False, description="Apply the learned window: once a session has seen enough samples "
                           "(and then every learn_interval_s), re-install its spec with "
                           "max_delay = the recommended one, through the normal admission "
                           "path (budgets, refusals); off: the window is only reported.")
    learn_interval_s: float = Field(
        30.0, gt=0, description="Least time between two learned-window changes of a session.")

    # logs
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    log_format: Literal["kv", "json"] = "kv"

    @field_validator("instance")
    @classmethod
    def _check_instance(cls, v: str) -> str:
        if not re.fullmatch(NAME_PATTERN, v):
            raise ValueError(f"must match {NAME_PATTERN}")
        return v

    @field_validator("peers")
    @classmethod
    def _check_peers(cls, v: list[str]) -> list[str]:
        for p in v:
            if not re.fullmatch(NAME_PATTERN, p):
                raise ValueError(f"{p!r} must match {NAME_PATTERN}")
        return v

    @field_validator("shard")
    @classmethod
    def _check_shard(cls, v: str | None) -> str | None:
        if v is None or v == "":
            return None
        m = _SHARD_RE.match(v)
        if not m or not (int(m.group(2)) >= 1 and int(m.group(1)) < int(m.group(2))):
            raise ValueError("must be 'i/N' with 0 <= i < N")
        return v

    @field_validator("metrics")
    @classmethod
    def _check_metrics(cls, v: str | None) -> str | None:
        if v is None or v == "":
            return None
        from pd_service.metrics import parse_address

        parse_address(v)  # ValueError names what is wrong
        return v

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper(cls, v: Any) -> Any:
        return v.upper() if isinstance(v, str) else v

    # derived values

    @property
    def shard_tuple(self) -> tuple[int, int] | None:
        if self.shard is None:
            return None
        i, n = self.shard.split("/")
        return int(i), int(n)

    @property
    def effective_state_dir(self) -> Path:
        return self.state_dir if self.state_dir is not None else default_state_dir() / self.instance

    @property
    def zenoh(self) -> ZenohOptions:
        """The Zenoh fields as the option group's :class:`ZenohOptions`."""
        return ZenohOptions(mode=self.mode, listen=tuple(self.listen or ()),
                            connect=tuple(self.connect), config_file=self.zenoh_config,
                            multicast=self.multicast, user=self.user,
                            password=self.password if self.password is not None
                            else os.environ.get(PASSWORD_ENV))



    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Highest first: flags (init kwargs) > environment > file. Outside
        :func:`load_settings` only the init kwargs (a plain model)."""
        layers = _LAYERS.get()
        if layers is None:
            return (init_settings,)
        sources: list[PydanticBaseSettingsSource] = [
            _Traced(init_settings, "flags", layers.origin),
            _Traced(_EnvSource(settings_cls, layers.environ), "environment", layers.origin),
        ]
        if layers.file is not None:
            file_cls = TomlConfigSettingsSource if layers.file.suffix == ".toml" \
                else JsonConfigSettingsSource
            sources.append(_Traced(file_cls(settings_cls, layers.file), layers.file_label,
                                   layers.origin))
        return tuple(sources)


_LIST_FIELDS = {"listen", "connect", "peers"}


@dataclass(slots=True)
class _Layers:
    """What one :func:`load_settings` call layers, and where each given field came from."""

    environ: Mapping[str, str]
    file: Path | None
    origin: dict[str, str] = field(default_factory=dict)

    @property
    def file_label(self) -> str:
        return f"file {str(self.file)!r}"


_LAYERS: ContextVar[_Layers | None] = ContextVar("pd_service_settings_layers", default=None)


@contextmanager
def _layering(layers: _Layers) -> Iterator[None]:
    token = _LAYERS.set(layers)
    try:
        yield
    finally:
        _LAYERS.reset(token)


class _EnvSource(EnvSettingsSource):
    """``PD_SERVICE_<FIELD>`` read from a given mapping; list fields split on commas."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str]) -> None:
        self._environ = environ
        super().__init__(settings_cls, case_sensitive=False, env_prefix=ENV_PREFIX)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        return {k.lower(): v for k, v in self._environ.items()}

    def prepare_field_value(self, field_name: str, field: FieldInfo, value: Any,
                            value_is_complex: bool) -> Any:
        if field_name in _LIST_FIELDS and isinstance(value, str):
            return [x.strip() for x in value.split(",") if x.strip()]
        return super().prepare_field_value(field_name, field, value, value_is_complex)


class _Traced(PydanticBaseSettingsSource):
    """A source that notes which fields it gave (pydantic-settings merges the layers
    without saying where a value came from; the error messages name the layer)."""

    def __init__(self, inner: PydanticBaseSettingsSource, label: str,
                 origin: dict[str, str]) -> None:
        super().__init__(inner.settings_cls)
        self.inner, self.label, self.origin = inner, label, origin

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return self.inner.get_field_value(field, field_name)

    def __call__(self) -> dict[str, Any]:
        values = self.inner()
        for k in values:  # sources are called highest priority first
            self.origin.setdefault(k, self.label)
        return values


def _check_file(p: Path) -> None:
    """The file sources skip a missing file and raise their parser's errors: say which file
    and why instead."""
    kind = "TOML" if p.suffix == ".toml" else "JSON"
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"config file {str(p)!r}: cannot read ({exc.strerror})") from None
    try:
        data = tomllib.loads(text) if kind == "TOML" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"config file {str(p)!r}: not valid {kind} ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(p)!r}: expected a table of settings")


def load_settings(
    flags: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
    config_file: str | Path | None = None,
) -> Settings:
    """Layer defaults < file < env < flags. ``flags`` holds only what was given on the
    command line (None values are ignored). The file is ``config_file``, else
    ``$PD_SERVICE_CONFIG``, else none."""
    environ = os.environ if environ is None else environ
    unknown = sorted(k for k in environ if k.upper().startswith(ENV_PREFIX)
                     and k.upper()[len(ENV_PREFIX):].lower() not in Settings.model_fields
                     and k.upper() not in NOT_SETTINGS_ENV)
    if unknown:  # a misspelt or retired variable would otherwise be ignored silently
        raise ConfigError(f"environment: unknown setting {unknown[0]!r} (settings: "
                          "docs/service.md, 'Settings')")
    given = {k: v for k, v in (flags or {}).items() if v is not None}
    path = config_file or environ.get(ENV_PREFIX + "CONFIG")
    layers = _Layers(environ, Path(path) if path else None)
    if layers.file is not None:
        _check_file(layers.file)
    try:
        with _layering(layers):
            return Settings(**given)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        name = str(err["loc"][0]) if err["loc"] else ""
        where = layers.origin.get(name, "defaults")
        if err["type"] == "extra_forbidden":
            raise ConfigError(f"{where}: unknown setting {name!r}") from None
        loc = ".".join(str(p) for p in err["loc"]) or "settings"
        raise ConfigError(f"{loc} ({where}): {err['msg']}") from None
