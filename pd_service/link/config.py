"""pd-link configuration: TOML or JSON, netem-style names.  See docs/link.md for every field.

Example (TOML)::

    seed = 7
    step_ms = 50

    [[downlink]]
    name = "camera"
    match = "robot/*/*/sensor/camera"
    delay = "10 steps"
    loss = "1%"

    [[uplink]]
    name = "commands"
    delay = "10 steps"

Units: percentages are percent (netem style): ``loss = 1`` and ``loss = "1%"`` both mean 1 %.
Times are ms when a bare number, else a string with a unit: ``ns``, ``us``, ``ms``, ``s``,
``step``/``steps`` (needs ``step_ms``).  Rates need a unit (see :func:`parse_rate`).

The document is read by strict pydantic models (unknown fields refused); a
``ValidationError`` becomes a :class:`~pd_service.errors.ConfigError` whose message names the
field (``downlink[0] (camera).delay: ...``).  The result is a :class:`LinkConfig` of
:class:`Rule` objects carrying the model's :class:`~pd_service.link.model.LinkParams`.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import astuple, dataclass, fields, replace
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, cast, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    PlainSerializer,
    PlainValidator,
    PrivateAttr,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from pd_service.errors import ConfigError
from pd_service.transport.keyexpr import check_keyexpr, intersects
from pd_service.wire import keys

from .model import (
    NS_PER_MS,
    TABLE_LIMIT,
    DelaySpec,
    Distribution,
    FourStateLoss,
    GilbertElliott,
    LinkParams,
    LossSpec,
    Outage,
    OutageMode,
    RandomLoss,
    Rate,
)

Direction = Literal["downlink", "uplink"]
DIRECTIONS: tuple[Direction, ...] = ("downlink", "uplink")


# --- scalar parsers (raise ConfigError, a ValueError: pydantic adds the field path) ---------

_TIME_UNITS_NS = {"ns": 1, "us": 1_000, "µs": 1_000, "ms": NS_PER_MS, "s": 1_000_000_000}
_TIME_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zµ]+)?\s*$")


def parse_time_ns(value: Any, step_ms: float | None = None) -> int:
    """A duration -> integer ns.  Number = ms; str = number + unit (ns, us, ms, s, step[s])."""
    if isinstance(value, bool) or value is None:
        raise ConfigError(f"expected a duration, got {value!r}")
    if isinstance(value, int | float):
        ms = float(value)
        if not math.isfinite(ms) or ms < 0:
            raise ConfigError(f"duration must be finite and >= 0, got {value!r}")
        return round(ms * NS_PER_MS)
    if not isinstance(value, str):
        raise ConfigError(f"expected a duration, got {value!r}")
    m = _TIME_RE.match(value)
    if m is None:
        raise ConfigError(f"cannot read duration {value!r} (e.g. '50ms', '10 steps')")
    number, unit = float(m.group(1)), (m.group(2) or "ms")
    if unit in ("step", "steps"):
        if step_ms is None:
            raise ConfigError(f"{value!r} is in steps but step_ms is not set")
        return round(number * step_ms * NS_PER_MS)
    if unit not in _TIME_UNITS_NS:
        raise ConfigError(f"unknown time unit {unit!r} (ns, us, ms, s, steps)")
    return round(number * _TIME_UNITS_NS[unit])


def parse_percent(value: Any) -> float:
    """A probability in netem's percent: ``5``, ``5.0``, ``"5%"`` -> 0.05."""
    if isinstance(value, bool) or value is None:
        raise ConfigError(f"expected a percentage, got {value!r}")
    if isinstance(value, str):
        text = value.strip().removesuffix("%")
        try:
            number = float(text)
        except ValueError:
            raise ConfigError(f"cannot read percentage {value!r} (e.g. '5%')") from None
    elif isinstance(value, int | float):
        number = float(value)
    else:
        raise ConfigError(f"expected a percentage, got {value!r}")
    if not math.isfinite(number) or number < 0 or number > 100:
        raise ConfigError(f"percentage must be in [0, 100], got {value!r}")
    return number / 100.0


_RATE_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zA-Z/]+)\s*$")
_BIT_UNITS = {"bit": 1, "kbit": 1e3, "mbit": 1e6, "gbit": 1e9}
_BYTE_UNITS = {"bps": 1, "kbps": 1e3, "mbps": 1e6, "gbps": 1e9}  # tc: "bps" = BYTES per second
_MSG_UNITS = ("msg/s", "msgps", "pps")


def parse_rate(value: Any, overhead: int = 0) -> Rate:
    """``"1mbit"`` (bits/s: bit, kbit, mbit, gbit), ``"125kbps"`` (BYTES/s as in tc: bps, kbps,
    mbps, gbps) or ``"200msg/s"`` (also ``msgps``, ``pps``) -> :class:`Rate`."""
    if not isinstance(value, str):
        raise ConfigError(
            f"a rate needs a unit, e.g. '1mbit', '125kbps' (bytes/s) or '100msg/s'; got {value!r}"
        )
    m = _RATE_RE.match(value)
    if m is None:
        raise ConfigError(f"cannot read rate {value!r} (e.g. '1mbit', '100msg/s')")
    number, unit = float(m.group(1)), m.group(2).lower()
    try:
        if unit in _BIT_UNITS:
            return Rate(bytes_per_s=number * _BIT_UNITS[unit] / 8.0, overhead_bytes=overhead)
        if unit in _BYTE_UNITS:
            return Rate(bytes_per_s=number * _BYTE_UNITS[unit], overhead_bytes=overhead)
        if unit in _MSG_UNITS:
            return Rate(msgs_per_s=number, overhead_bytes=overhead)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    raise ConfigError(
        f"unknown rate unit {unit!r} (bit kbit mbit gbit | bps kbps mbps gbps = bytes/s | msg/s)"
    )


def format_ns(ns: int) -> str:
    """Integer ns -> exact ms string (``500000000`` -> ``"500ms"``, ``1500`` -> ``"0.0015ms"``)."""
    whole, frac = divmod(int(ns), NS_PER_MS)
    return f"{whole}.{frac:06d}".rstrip("0").rstrip(".") + "ms"


def format_percent(p: float) -> str:
    return f"{p * 100:.12g}%"


def format_rate(rate: Rate) -> str:
    if rate.msgs_per_s is not None:
        return f"{rate.msgs_per_s:.12g}msg/s"
    assert rate.bytes_per_s is not None
    return f"{rate.bytes_per_s * 8:.12g}bit"


def _duration(value: Any, info: ValidationInfo) -> int:
    return parse_time_ns(value, (info.context or {}).get("step_ms"))


# each field type reads the document's form and writes it back (``Rule.to_dict``)
Percent = Annotated[float, PlainValidator(parse_percent), PlainSerializer(format_percent)]
Duration = Annotated[int, PlainValidator(_duration), PlainSerializer(format_ns)]
KeyExpr = Annotated[str, PlainValidator(check_keyexpr)]
RateField = Annotated[Rate, PlainValidator(parse_rate), PlainSerializer(format_rate)]


class _Doc(BaseModel):
    """A table of the document: strict types, unknown fields refused."""

    model_config = ConfigDict(strict=True, extra="forbid")


# --- key mappings ------------------------------------------------------------------------

_PLACEHOLDER = re.compile(r"\{(p?)(\d+)\}")


class KeyMapping(_Doc):
    """Subscribe to ``subscribe`` and publish each sample on ``publish``'s image of its key.

    ``publish``: ``"operator"`` (:func:`keys.to_operator_side`), ``"robot"``
    (:func:`keys.to_robot_side`), or a template where ``{1}``, ``{2}``, ... are the chunks the
    1st, 2nd, ... ``*`` of ``subscribe`` matched, and ``{p1}``, ``{p2}``, ... the partition
    chunk ``p<k>`` of that chunk as a session name (protocol.md §3):
    ``"pd/{p1}/{1}/sensor/{2}"`` maps ``lab/r2/imu`` (subscribed as ``lab/*/*``) to
    ``pd/p37/r2/sensor/imu`` (P = 64).
    """

    model_config = ConfigDict(frozen=True)

    direction: Direction
    subscribe: KeyExpr
    publish: str = Field(min_length=1)

    @model_validator(mode="after")
    def _check_template(self) -> KeyMapping:
        if self.publish in ("operator", "robot"):
            return self
        if "**" in self.subscribe.split("/"):
            raise ValueError("a template mapping cannot subscribe with '**'")
        stars = self.subscribe.split("/").count("*")
        for m in _PLACEHOLDER.finditer(self.publish):
            if not 1 <= int(m.group(2)) <= stars:
                raise ValueError(f"publish: {m.group(0)} but {self.subscribe!r} has {stars} '*'")
        check_keyexpr(_PLACEHOLDER.sub("x", self.publish))
        if "*" in self.publish.replace("$*", "*"):
            raise ValueError("publish: the output key cannot contain wildcards")
        return self

    def map_key(self, key: str) -> str:
        """Output key for input ``key``; raises ValueError if the key does not map."""
        if self.publish == "operator":
            return keys.to_operator_side(key)
        if self.publish == "robot":
            return keys.to_robot_side(key)
        pattern = self.subscribe.split("/")
        chunks = key.split("/")
        if len(pattern) != len(chunks):
            raise ValueError(f"key {key!r} does not match {self.subscribe!r}")
        caught = [c for p, c in zip(pattern, chunks, strict=True) if p == "*"]
        return _PLACEHOLDER.sub(lambda m: self._chunk(caught[int(m.group(2)) - 1], m.group(1)),
                                self.publish)

    @staticmethod
    def _chunk(caught: str, partition: str) -> str:
        """A caught chunk, or (``{p<n>}``) its partition chunk as a session's (KeyError_,
        a ValueError, if it is no name)."""
        return keys.partition_chunk(keys.partition_of(caught)) if partition else caught

    def to_dict(self) -> dict[str, str]:
        return self.model_dump()


DEFAULT_MAPPINGS: tuple[KeyMapping, ...] = (
    KeyMapping(direction="downlink", subscribe=keys.ROBOT_ALL_SENSORS, publish="operator"),
    KeyMapping(direction="downlink", subscribe=keys.ROBOT_ALL_ECHOES, publish="operator"),
    KeyMapping(direction="downlink", subscribe=keys.ROBOT_ALL_CAMERAS, publish="operator"),
    KeyMapping(direction="uplink", subscribe=keys.ALL_COMMANDS, publish="robot"),
)


# --- loss models (a tagged union on "model"; each table becomes the model's dataclass) -------


class _LossDoc(_Doc):
    """A loss table; validating it builds the model's loss dataclass (:attr:`spec`), whose
    fields are the table's after ``model``, in order."""

    spec_type: ClassVar[type[LossSpec]]
    model: str
    _spec: LossSpec = PrivateAttr()

    @model_validator(mode="after")
    def _build(self) -> _LossDoc:
        self._spec = self.build()
        return self

    def build(self) -> LossSpec:
        raise NotImplementedError

    @property
    def spec(self) -> LossSpec:
        return self._spec

    @classmethod
    def of(cls, spec: LossSpec) -> LossTable:
        """The table of a loss dataclass (every field written, as ``to_dict`` does)."""
        doc = next(c for c in cls.__subclasses__() if c.spec_type is type(spec))
        names = [n for n in doc.model_fields if n != "model"]
        return cast(LossTable, doc.model_construct(
            model=get_args(doc.model_fields["model"].annotation)[0],
            **dict(zip(names, astuple(spec), strict=True))))


class _RandomLossDoc(_LossDoc):
    spec_type = RandomLoss
    model: Literal["random"] = "random"
    percent: Percent
    correlation: Percent = 0.0

    def build(self) -> LossSpec:
        return RandomLoss(self.percent, self.correlation)


class _GilbertElliottDoc(_LossDoc):
    spec_type = GilbertElliott
    model: Literal["gemodel"]
    p: Percent
    r: Percent | None = None  # netem: 1 - p
    one_minus_h: Percent = Field(1.0, alias="1-h")
    one_minus_k: Percent = Field(0.0, alias="1-k")

    def build(self) -> LossSpec:
        r = 1.0 - self.p if self.r is None else self.r
        return GilbertElliott(self.p, r, self.one_minus_h, self.one_minus_k)


class _FourStateDoc(_LossDoc):
    spec_type = FourStateLoss
    model: Literal["state"]
    p13: Percent
    p31: Percent | None = None  # netem: 1 - p13
    p32: Percent = 0.0
    p23: Percent = 1.0
    p14: Percent = 0.0

    def build(self) -> LossSpec:
        p31 = 1.0 - self.p13 if self.p31 is None else self.p31
        return FourStateLoss(self.p13, p31, self.p32, self.p23, self.p14)


LOSS_MODELS = ("random", "gemodel", "state")
LossTable = _RandomLossDoc | _GilbertElliottDoc | _FourStateDoc


def _loss_tag(value: Any) -> str:
    """Which member of the loss union reads ``value``: a table by its ``model`` (default
    random), anything else as the shorthand percentage (``loss = "1%"``); when writing a
    rule back, a loss table by its own."""
    if isinstance(value, _LossDoc):
        return value.model
    if isinstance(value, Mapping):
        return str(value.get("model", "random"))
    return "percent"


Loss = Annotated[
    Annotated[_RandomLossDoc, Tag("random")]
    | Annotated[_GilbertElliottDoc, Tag("gemodel")]
    | Annotated[_FourStateDoc, Tag("state")]
    | Annotated[Percent, Tag("percent")],
    Discriminator(_loss_tag, custom_error_type="loss_model",
                  custom_error_message="model must be 'random', 'gemodel' or 'state'"),
]  # fmt: skip


# --- outages ---------------------------------------------------------------------------


class _OutageDoc(_Doc):
    """``{at, for, every}``; validating it builds the model's :class:`Outage` (:attr:`window`)."""

    at: Duration = 0
    for_: Duration = Field(alias="for")
    every: Duration = Field(0, exclude_if=lambda every: every == 0)
    _window: Outage = PrivateAttr()

    @model_validator(mode="after")
    def _build(self) -> _OutageDoc:
        self._window = Outage(self.at, self.for_, self.every)
        return self

    @property
    def window(self) -> Outage:
        return self._window

    @classmethod
    def of(cls, window: Outage) -> _OutageDoc:
        return cls.model_construct(at=window.start_ns, for_=window.duration_ns,
                                   every=window.every_ns)


def _as_list(value: Any) -> Any:
    """A single table where a list of tables is expected (``outage = {at, for}``)."""
    return [value] if isinstance(value, Mapping) else value


# --- rules -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Rule:
    """One rule: the messages of its direction whose source key matches ``match`` get
    ``params``.  ``shared``: one model state for all keys matched (one netem qdisc) instead of
    one per key."""

    name: str
    match: str
    params: LinkParams
    shared: bool = False

    def matches(self, key: str) -> bool:
        return intersects(self.match, key)

    def to_dict(self) -> dict[str, Any]:
        """Normalised form (ms strings, percent strings) that parses back to the same rule."""
        return _RuleDoc.of(self).to_dict()


#: LinkParams fields a rule table holds as they are (the others are built from its fields)
_AS_IS = tuple(f.name for f in fields(LinkParams) if f.name not in ("delay", "loss", "rate",
                                                                     "outages"))
#: Fields refused unless the one named is set too (tc's refusals); written only with it.
_NEEDS = {"distribution": "jitter", "gap": "reorder", "packet_overhead": "rate"}
#: Fields written whenever the one named is (as netem shows them), even with their default.
_WRITTEN_WITH = {"distribution": "jitter", "gap": "reorder", "outage_mode": "outage"}


class _RuleDoc(_Doc):
    """One rule table (netem's names); validating it builds the :class:`LinkParams`, and
    :meth:`of` / :meth:`to_dict` write one back (fields in this order)."""

    name: str = Field(min_length=1)
    match: KeyExpr = "**"
    shared: bool = False
    delay: Duration = 0
    jitter: Duration = 0
    distribution: Distribution = "uniform"
    delay_correlation: Percent = 0.0
    loss: Loss | None = None
    loss_correlation: Percent | None = None
    duplicate: Percent = 0.0
    duplicate_correlation: Percent = 0.0
    reorder: Percent = 0.0
    reorder_correlation: Percent = 0.0
    corrupt: Percent = 0.0
    corrupt_correlation: Percent = 0.0
    gap: int = 1
    corrupt_bits: int = 1
    rate: RateField | None = None
    packet_overhead: int = 0
    outage: Annotated[list[_OutageDoc], BeforeValidator(_as_list)] = []
    outage_mode: OutageMode = "drop"
    in_order: bool = False

    _params: LinkParams = PrivateAttr()

    @model_validator(mode="after")
    def _build_params(self) -> _RuleDoc:
        given = self.model_fields_set
        for name, needed in _NEEDS.items():
            if name in given and not getattr(self, needed):
                raise ValueError(f"{name} given without {needed}")
        loss: LossSpec | None = None
        if isinstance(self.loss, float):  # shorthand: loss = "1%" [loss_correlation = ...]
            if self.loss > 0:
                loss = RandomLoss(self.loss, self.loss_correlation or 0.0)
        elif self.loss_correlation is not None:
            raise ValueError("use loss.correlation inside the loss table" if self.loss is not None
                             else "loss_correlation given without loss")
        elif self.loss is not None:
            loss = self.loss.spec
        rate = None if self.rate is None else replace(self.rate, overhead_bytes=self.packet_overhead)
        delay = DelaySpec(self.delay, self.jitter, self.delay_correlation, self.distribution)
        self._params = LinkParams(delay, loss, rate=rate,
                                  outages=tuple(w.window for w in self.outage),
                                  **{n: getattr(self, n) for n in _AS_IS})
        return self

    def rule(self) -> Rule:
        return Rule(self.name, self.match, self._params, self.shared)

    @classmethod
    def of(cls, rule: Rule) -> _RuleDoc:
        """The table of ``rule`` (unvalidated: ``rule`` was)."""
        p, d = rule.params, rule.params.delay
        return cls.model_construct(
            name=rule.name, match=rule.match, shared=rule.shared, delay=d.delay_ns,
            jitter=d.jitter_ns, distribution=d.distribution, delay_correlation=d.correlation,
            loss=None if p.loss is None else _LossDoc.of(p.loss), rate=p.rate,
            packet_overhead=0 if p.rate is None else p.rate.overhead_bytes,
            outage=[_OutageDoc.of(w) for w in p.outages], **{n: getattr(p, n) for n in _AS_IS})

    def to_dict(self) -> dict[str, Any]:
        """``name``, ``match`` and the fields that differ from their defaults (see
        :data:`_NEEDS`, :data:`_WRITTEN_WITH`), in the document's form."""
        written: set[str] = {"name", "match"}
        for name, info in type(self).model_fields.items():
            needed = _NEEDS.get(name)
            if ((getattr(self, name) != info.default and (needed is None or needed in written))
                    or _WRITTEN_WITH.get(name) in written):
                written.add(name)
        return self.model_dump(by_alias=True, include=written)


def _rule_tables(value: Any, info: ValidationInfo) -> Any:
    """``[[downlink]]`` tables (or one table); a rule without a name gets ``downlink-<i>``."""
    value = _as_list(value)
    if not isinstance(value, list):
        raise ValueError(f"must be a list of rule tables ([[{info.field_name}]])")
    return [{"name": f"{info.field_name}-{i}", **r} if isinstance(r, Mapping) else r
            for i, r in enumerate(value)]  # fmt: skip


def _unique_names(rules: list[_RuleDoc]) -> list[_RuleDoc]:
    names = [r.name for r in rules]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"rule names must be unique, repeated: {dupes}")
    return rules


RuleList = Annotated[list[_RuleDoc], BeforeValidator(_rule_tables), AfterValidator(_unique_names)]


# --- the whole configuration -----------------------------------------------------------


_SIZE_UNITS = {"b": 1, "kb": 1000, "kib": 1024, "mb": 1000**2, "mib": 1024**2,
               "gb": 1000**3, "gib": 1024**3}
_SIZE_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*$")


def parse_size(value: Any) -> int:
    """A size in bytes: an integer, or a string with a unit (``"64MiB"``, ``"500kB"``, ``"10b"``)."""
    if isinstance(value, bool):
        raise ConfigError(f"expected a size in bytes, got {value!r}")
    if isinstance(value, int):
        number = float(value)
    elif isinstance(value, str) and (m := _SIZE_RE.match(value)) is not None:
        unit = (m.group(2) or "b").lower()
        if unit not in _SIZE_UNITS:
            raise ConfigError(f"unknown size unit {m.group(2)!r} (b, kB, KiB, MB, MiB, GB, GiB)")
        number = float(m.group(1)) * _SIZE_UNITS[unit]
    else:
        raise ConfigError(f"expected a size in bytes (e.g. 65536 or '64MiB'), got {value!r}")
    if not math.isfinite(number) or number < 1:
        raise ConfigError(f"size must be >= 1 byte, got {value!r}")
    return int(number)


@dataclass(frozen=True, slots=True)
class Limits:
    """What one pd-link process may hold, whatever the rules and the traffic.

    ``max_held_messages``, ``max_held_bytes``: messages waiting for their release time (the
    heap) and their bytes (payload + attachment + :data:`HELD_OVERHEAD_BYTES` per message for
    the entry's own objects).  A message that would exceed either is dropped and counted
    (``dropped_capacity``).
    ``max_delay_ns``: a rule whose largest delay (``delay + jitter * max t``) exceeds this is refused when the
    configuration is read (file or rules query).
    ``max_keys``: input keys relayed at once, each with its route, per-key model and output
    publisher; beyond it the least recently used key is forgotten (its publisher undeclared,
    its model state restarted when it comes back) and counted (``keys_evicted``).
    """

    max_held_messages: int = 100_000
    max_held_bytes: int = 64 * 1024 * 1024
    max_delay_ns: int = 60_000_000_000
    max_keys: int = 1024

    def to_dict(self) -> dict[str, Any]:
        return {"max_held_messages": self.max_held_messages,
                "max_held_bytes": self.max_held_bytes,
                "max_delay": format_ns(self.max_delay_ns),
                "max_keys": self.max_keys}  # fmt: skip


#: A held message's own objects, counted so that max_held_bytes tracks the memory really held.
HELD_OVERHEAD_BYTES = 640

_DEFAULT_LIMITS = Limits()


class _LimitsDoc(_Doc):
    """The ``[limits]`` table (every field optional, defaults of :class:`Limits`)."""

    max_held_messages: Annotated[int, Field(ge=1)] = _DEFAULT_LIMITS.max_held_messages
    max_held_bytes: Annotated[int, PlainValidator(parse_size)] = _DEFAULT_LIMITS.max_held_bytes
    max_delay: Duration = _DEFAULT_LIMITS.max_delay_ns
    max_keys: Annotated[int, Field(ge=1)] = _DEFAULT_LIMITS.max_keys

    def limits(self) -> Limits:
        return Limits(self.max_held_messages, self.max_held_bytes, self.max_delay,
                      self.max_keys)  # fmt: skip


class _ConfigDoc(_Doc):
    """The document.  Fields are validated in this order: ``step_ms`` is known (through the
    validation context) before the rules' durations in steps are read."""

    seed: int = 0
    step_ms: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    mapping: Annotated[list[KeyMapping], Field(min_length=1)] | None = None
    limits: _LimitsDoc | None = None
    downlink: RuleList = []
    uplink: RuleList = []

    @field_validator("step_ms")
    @classmethod
    def _share_step(cls, value: float | None, info: ValidationInfo) -> float | None:
        if isinstance(info.context, dict):
            info.context["step_ms"] = value
        return value


@dataclass(frozen=True, slots=True)
class LinkConfig:
    """A parsed configuration: seed, step, key mappings and the rules of both directions."""

    seed: int = 0
    step_ms: float | None = None
    mappings: tuple[KeyMapping, ...] = DEFAULT_MAPPINGS
    downlink: tuple[Rule, ...] = ()
    uplink: tuple[Rule, ...] = ()
    limits: Limits = _DEFAULT_LIMITS

    def rules(self, direction: Direction) -> tuple[Rule, ...]:
        return self.downlink if direction == "downlink" else self.uplink

    def rule_for(self, direction: Direction, key: str) -> tuple[int, Rule] | None:
        """First rule of ``direction`` matching ``key`` (index, rule), or None."""
        for i, rule in enumerate(self.rules(direction)):
            if rule.matches(key):
                return i, rule
        return None

    def to_dict(self) -> dict[str, Any]:
        """Normalised JSON-able form; ``parse_config(cfg.to_dict()) == cfg``."""
        out: dict[str, Any] = {"seed": self.seed}
        if self.step_ms is not None:
            out["step_ms"] = self.step_ms
        out["mapping"] = [m.to_dict() for m in self.mappings]
        out["limits"] = self.limits.to_dict()
        out["downlink"] = [r.to_dict() for r in self.downlink]
        out["uplink"] = [r.to_dict() for r in self.uplink]
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


def parse_config(doc: Any, *, base: LinkConfig | None = None) -> LinkConfig:
    """A decoded document (dict) -> :class:`LinkConfig` (raises :class:`ConfigError` naming
    the field).

    With ``base`` (runtime replacement): ``seed`` and ``step_ms`` default to the base's, and
    ``mapping`` and ``limits`` may be omitted or must equal the base's (subscriptions and
    limits are fixed at start: a rules query cannot raise them).

    A rule whose largest delay ``delay + jitter * max t`` exceeds ``limits.max_delay`` is refused.
    """
    if not isinstance(doc, Mapping):
        raise ConfigError("the configuration must be a table / JSON object")
    if base is not None:
        doc = {"seed": base.seed, "step_ms": base.step_ms} | dict(doc)
    try:
        d = _ConfigDoc.model_validate(doc, context={"step_ms": None})
    except ValidationError as e:
        raise ConfigError("; ".join(_describe(err, doc) for err in e.errors())) from None
    mappings = DEFAULT_MAPPINGS if base is None else base.mappings
    if d.mapping is not None:
        if base is not None and tuple(d.mapping) != base.mappings:
            raise ConfigError("mapping cannot be changed at runtime; restart pd-link")
        mappings = tuple(d.mapping)
    limits = _DEFAULT_LIMITS if base is None else base.limits
    if d.limits is not None:
        if base is not None and d.limits.limits() != base.limits:
            raise ConfigError("limits cannot be changed at runtime; restart pd-link")
        limits = d.limits.limits()
    for direction in DIRECTIONS:
        for i, r in enumerate(getattr(d, direction)):
            # the largest delay the rule can draw: t <= 1 (uniform) or TABLE_LIMIT (tables)
            worst = r.delay + math.ceil(r.jitter * (1.0 if r.distribution == "uniform"
                                                    else TABLE_LIMIT))
            if worst > limits.max_delay_ns:
                raise ConfigError(
                    f"{direction}[{i}] ({r.name}).delay: the largest delay the rule can draw, "
                    f"{format_ns(worst)}, "
                    f"exceeds limits.max_delay = {format_ns(limits.max_delay_ns)} (raise "
                    "limits.max_delay in the configuration file to allow it)")
    return LinkConfig(d.seed, d.step_ms, mappings, tuple(r.rule() for r in d.downlink),
                      tuple(r.rule() for r in d.uplink), limits)  # fmt: skip


def _describe(err: Any, doc: Mapping[str, Any]) -> str:
    """One pydantic error as ``path: reason``; the path is built from ``loc`` in the document's
    terms (``downlink[0] (camera).loss.p``: list indices in brackets, the rule's name after its
    index, the loss union's tag left out)."""
    loc: tuple[Any, ...] = err["loc"]
    kind, value = err["type"], err.get("input")
    if kind == "missing":
        loc, reason = loc[:-1], f"needs {loc[-1]!r}"
    elif kind == "extra_forbidden":
        loc, reason = loc[:-1], f"unknown field {loc[-1]!r}"
    elif kind == "value_error":
        reason = str(err["ctx"]["error"])
    elif kind == "model_type":
        reason = f"expected a table, got {value!r}"
    elif kind == "loss_model":
        reason = f"{err['msg']}, got {value.get('model')!r}"
    elif kind == "bool_type":
        reason = f"must be true or false, got {value!r}"
    else:
        reason = f"{err['msg']}, got {value!r}"
    path = ""
    node: Any = doc
    for i, item in enumerate(loc):
        if isinstance(item, int):
            path += f"[{item}]"
            node = _as_list(node)[item] if isinstance(node, Mapping | list) else None
            if len(loc) > 1 and i == 1 and loc[0] in DIRECTIONS and isinstance(node, Mapping):
                path += f" ({node.get('name', f'{loc[0]}-{item}')})"
        elif not (i and loc[i - 1] == "loss" and item in (*LOSS_MODELS, "percent")):
            path += f".{item}" if path else str(item)
            node = node.get(item) if isinstance(node, Mapping) else None
    return f"{path or 'configuration'}: {reason}"


def decode_document(data: bytes | str) -> dict[str, Any]:
    """Decode JSON (if it starts with ``{``) or TOML text into a dict."""
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError:
            raise ConfigError("the configuration is not UTF-8 text") from None
    text = data.lstrip()
    if text.startswith("{"):
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"invalid JSON: {e}") from None
    else:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"invalid TOML: {e}") from None
    if not isinstance(doc, dict):
        raise ConfigError("the configuration must be a table / JSON object")
    return doc


def load_config(path: str | Path) -> LinkConfig:
    """Read a ``.toml`` or ``.json`` file into a :class:`LinkConfig`."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read {p}: {e.strerror}") from None
    return parse_config(decode_document(data))
