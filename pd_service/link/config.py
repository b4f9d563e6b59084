"""pd-link configuration: TOML or JSON, netem-style names.  See docs/link.md for every field.

Example (TOML)::

    seed = 7
    step_ms = 50

    [[downlink]]
    name = "camera"
    match = "robot/*/sensor/camera"
    delay = "10 steps"
    loss = "1%"

    [[uplink]]
    name = "commands"
    delay = "10 steps"

Units: percentages are percent (netem style): ``loss = 1`` and ``loss = "1%"`` both mean 1 %.
Times are ms when a bare number, else a string with a unit: ``ns``, ``us``, ``ms``, ``s``,
``step``/``steps`` (needs ``step_ms``).  Rates need a unit (see :func:`parse_rate`).

No Zenoh here: key expressions are matched by :func:`keyexpr_matches`, which implements the
Zenoh 1.x rules this project uses (``*`` one chunk, ``**`` any number of chunks, ``$*`` inside
a chunk, and chunks starting with ``@`` never matched by a wildcard).
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

from pd_service.wire import keys

from .model import (
    DISTRIBUTIONS,
    NS_PER_MS,
    DelaySpec,
    FourStateLoss,
    GilbertElliott,
    LinkParams,
    LossSpec,
    Outage,
    RandomLoss,
    Rate,
)

Direction = Literal["downlink", "uplink"]
DIRECTIONS: tuple[Direction, ...] = ("downlink", "uplink")


class ConfigError(ValueError):
    """A pd-link configuration that cannot be used; the message names the field."""


# --- scalar parsers --------------------------------------------------------------------

_TIME_UNITS_NS = {"ns": 1, "us": 1_000, "µs": 1_000, "ms": NS_PER_MS, "s": 1_000_000_000}
_TIME_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zµ]+)?\s*$")


def parse_time_ns(value: Any, what: str, step_ms: float | None = None) -> int:
    """A duration -> integer ns.  Number = ms; str = number + unit (ns, us, ms, s, step[s])."""
    if isinstance(value, bool) or value is None:
        raise ConfigError(f"{what}: expected a duration, got {value!r}")
    if isinstance(value, int | float):
        ms = float(value)
        if not math.isfinite(ms) or ms < 0:
            raise ConfigError(f"{what}: duration must be finite and >= 0, got {value!r}")
        return round(ms * NS_PER_MS)
    if not isinstance(value, str):
        raise ConfigError(f"{what}: expected a duration, got {value!r}")
    m = _TIME_RE.match(value)
    if m is None:
        raise ConfigError(f"{what}: cannot read duration {value!r} (e.g. '50ms', '10 steps')")
    number, unit = float(m.group(1)), (m.group(2) or "ms")
    if unit in ("step", "steps"):
        if step_ms is None:
            raise ConfigError(f"{what}: {value!r} is in steps but step_ms is not set")
        return round(number * step_ms * NS_PER_MS)
    if unit not in _TIME_UNITS_NS:
        raise ConfigError(f"{what}: unknown time unit {unit!r} (ns, us, ms, s, steps)")
    return round(number * _TIME_UNITS_NS[unit])


def parse_percent(value: Any, what: str) -> float:
    """A probability in netem's percent: ``5``, ``5.0``, ``"5%"`` -> 0.05."""
    if isinstance(value, bool) or value is None:
        raise ConfigError(f"{what}: expected a percentage, got {value!r}")
    if isinstance(value, str):
        text = value.strip()
        if text.endswith("%"):
            text = text[:-1]
        try:
            number = float(text)
        except ValueError:
            raise ConfigError(f"{what}: cannot read percentage {value!r} (e.g. '5%')") from None
    elif isinstance(value, int | float):
        number = float(value)
    else:
        raise ConfigError(f"{what}: expected a percentage, got {value!r}")
    if not math.isfinite(number) or number < 0 or number > 100:
        raise ConfigError(f"{what}: percentage must be in [0, 100], got {value!r}")
    return number / 100.0


_RATE_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zA-Z/]+)\s*$")
_BIT_UNITS = {"bit": 1, "kbit": 1e3, "mbit": 1e6, "gbit": 1e9}
_BYTE_UNITS = {"bps": 1, "kbps": 1e3, "mbps": 1e6, "gbps": 1e9}  # tc: "bps" = BYTES per second
_MSG_UNITS = ("msg/s", "msgps", "pps")


def parse_rate(value: Any, what: str, overhead: int = 0) -> Rate:
    """``"1mbit"`` (bits/s: bit, kbit, mbit, gbit), ``"125kbps"`` (BYTES/s as in tc: bps, kbps,
    mbps, gbps) or ``"200msg/s"`` (also ``msgps``, ``pps``) -> :class:`Rate`."""
    if not isinstance(value, str):
        raise ConfigError(
            f"{what}: a rate needs a unit, e.g. '1mbit', '125kbps' (bytes/s) or '100msg/s'; "
            f"got {value!r}"
        )
    m = _RATE_RE.match(value)
    if m is None:
        raise ConfigError(f"{what}: cannot read rate {value!r} (e.g. '1mbit', '100msg/s')")
    number, unit = float(m.group(1)), m.group(2).lower()
    try:
        if unit in _BIT_UNITS:
            return Rate(bytes_per_s=number * _BIT_UNITS[unit] / 8.0, overhead_bytes=overhead)
        if unit in _BYTE_UNITS:
            return Rate(bytes_per_s=number * _BYTE_UNITS[unit], overhead_bytes=overhead)
        if unit in _MSG_UNITS:
            return Rate(msgs_per_s=number, overhead_bytes=overhead)
    except ValueError as e:
        raise ConfigError(f"{what}: {e}") from None
    raise ConfigError(
        f"{what}: unknown rate unit {unit!r} (bit kbit mbit gbit | bps kbps mbps gbps = bytes/s"
        f" | msg/s)"
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


# --- key expressions -------------------------------------------------------------------


def check_keyexpr(expr: Any, what: str) -> str:
    """Basic shape check of a key expression (non-empty chunks, no leading/trailing '/')."""
    if not isinstance(expr, str) or not expr:
        raise ConfigError(f"{what}: expected a key expression, got {expr!r}")
    chunks = expr.split("/")
    if any(c == "" for c in chunks):
        raise ConfigError(f"{what}: {expr!r} has an empty chunk (leading, trailing or '//')")
    for c in chunks:
        if c in ("*", "**"):
            continue
        if "**" in c:
            raise ConfigError(f"{what}: {expr!r}: '**' must be a whole chunk")
        if "*" in c.replace("$*", ""):
            raise ConfigError(f"{what}: {expr!r}: '*' must be a whole chunk (or '$*' inside one)")
        if any(ch in c for ch in "?#[]"):
            raise ConfigError(f"{what}: {expr!r}: characters ?, #, [ and ] are not allowed")
    return expr


@lru_cache(maxsize=4096)
def _chunk_regex(chunk: str) -> re.Pattern[str]:
    return re.compile("^" + ".*".join(re.escape(p) for p in chunk.split("$*")) + "$")


def _chunk_matches(pattern: str, chunk: str) -> bool:
    if pattern == "*":
        return not chunk.startswith("@")
    if "$*" in pattern:
        return not chunk.startswith("@") and _chunk_regex(pattern).match(chunk) is not None
    return pattern == chunk


def keyexpr_matches(pattern: str, key: str) -> bool:
    """Does the key expression ``pattern`` include the concrete key ``key``?"""
    return _match(tuple(pattern.split("/")), tuple(key.split("/")))


def _match(p: tuple[str, ...], k: tuple[str, ...]) -> bool:
    if not p:
        return not k
    head = p[0]
    if head == "**":
        # zero chunks, or swallow one (non-verbatim) chunk and try again
        if _match(p[1:], k):
            return True
        return bool(k) and not k[0].startswith("@") and _match(p, k[1:])
    return bool(k) and _chunk_matches(head, k[0]) and _match(p[1:], k[1:])


# --- mapping ---------------------------------------------------------------------------

_PLACEHOLDER = re.compile(r"\{(\d+)\}")


@dataclass(frozen=True, slots=True)
class KeyMapping:
    """Subscribe to ``subscribe`` and publish each sample on ``publish``'s image of its key.

    ``publish``: ``"operator"`` (:func:`keys.to_operator_side`), ``"robot"``
    (:func:`keys.to_robot_side`), or a template where ``{1}``, ``{2}``, ... are the chunks the
    1st, 2nd, ... ``*`` of ``subscribe`` matched (``"pd/{1}/sensor/{2}"``).
    """

    direction: Direction
    subscribe: str
    publish: str

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
        return _PLACEHOLDER.sub(lambda m: caught[int(m.group(1)) - 1], self.publish)

    def to_dict(self) -> dict[str, str]:
        return {"direction": self.direction, "subscribe": self.subscribe, "publish": self.publish}


DEFAULT_MAPPINGS: tuple[KeyMapping, ...] = (
    KeyMapping("downlink", keys.ROBOT_ALL_SENSORS, "operator"),
    KeyMapping("uplink", keys.ALL_COMMANDS, "robot"),
)


def _parse_mapping(raw: Any, i: int) -> KeyMapping:
    what = f"mapping[{i}]"
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{what}: expected a table with direction, subscribe, publish")
    _no_unknown(raw, {"direction", "subscribe", "publish"}, what)
    direction = raw.get("direction")
    if direction not in DIRECTIONS:
        raise ConfigError(f"{what}.direction must be 'downlink' or 'uplink', got {direction!r}")
    subscribe = check_keyexpr(raw.get("subscribe"), f"{what}.subscribe")
    publish = raw.get("publish")
    if not isinstance(publish, str) or not publish:
        raise ConfigError(f"{what}.publish: 'operator', 'robot' or a key template")
    if publish not in ("operator", "robot"):
        if "**" in subscribe.split("/"):
            raise ConfigError(f"{what}: a template mapping cannot subscribe with '**'")
        stars = subscribe.split("/").count("*")
        for m in _PLACEHOLDER.finditer(publish):
            if not 1 <= int(m.group(1)) <= stars:
                raise ConfigError(
                    f"{what}.publish: {{{m.group(1)}}} but {subscribe!r} has {stars} '*'"
                )
        check_keyexpr(_PLACEHOLDER.sub("x", publish), f"{what}.publish")
        if "*" in publish.replace("$*", "*"):
            raise ConfigError(f"{what}.publish: the output key cannot contain wildcards")
    return KeyMapping(direction, subscribe, publish)


# --- rules -----------------------------------------------------------------------------

RULE_FIELDS = frozenset(
    {
        "name", "match", "shared",
        "delay", "jitter", "delay_correlation", "distribution",
        "loss", "loss_correlation",
        "duplicate", "duplicate_correlation",
        "reorder", "reorder_correlation", "gap",
        "corrupt", "corrupt_correlation", "corrupt_bits",
        "rate", "packet_overhead",
        "outage", "outage_mode",
        "in_order",
    }
)  # fmt: skip
TOP_FIELDS = frozenset({"seed", "step_ms", "mapping", "downlink", "uplink"})


@dataclass(frozen=True, slots=True)
class Rule:
    """One rule: the messages of ``direction`` whose source key matches ``match`` get
    ``params``.  ``shared``: one model state for all keys matched (one netem qdisc) instead of
    one per key."""

    name: str
    direction: Direction
    match: str
    params: LinkParams
    shared: bool = False

    def matches(self, key: str) -> bool:
        return keyexpr_matches(self.match, key)

    def to_dict(self) -> dict[str, Any]:
        """Normalised form (ms strings, percent strings) that parses back to the same rule."""
        p = self.params
        out: dict[str, Any] = {"name": self.name, "match": self.match}
        if self.shared:
            out["shared"] = True
        d = p.delay
        if d.delay_ns:
            out["delay"] = format_ns(d.delay_ns)
        if d.jitter_ns:
            out["jitter"] = format_ns(d.jitter_ns)
            out["distribution"] = d.distribution
        if d.correlation:
            out["delay_correlation"] = format_percent(d.correlation)
        if p.loss is not None:
            out["loss"] = _loss_to_dict(p.loss)
        for name in ("duplicate", "reorder", "corrupt"):
            prob = getattr(p, name)
            if prob:
                out[name] = format_percent(prob)
            rho = getattr(p, f"{name}_correlation")
            if rho:
                out[f"{name}_correlation"] = format_percent(rho)
        if p.reorder:
            out["gap"] = p.gap
        if p.corrupt_bits != 1:
            out["corrupt_bits"] = p.corrupt_bits
        if p.rate is not None:
            out["rate"] = format_rate(p.rate)
            if p.rate.overhead_bytes:
                out["packet_overhead"] = p.rate.overhead_bytes
        if p.outages:
            out["outage"] = [
                {"at": format_ns(w.start_ns), "for": format_ns(w.duration_ns)}
                | ({"every": format_ns(w.every_ns)} if w.every_ns else {})
                for w in p.outages
            ]
        if p.outages or p.outage_mode != "drop":
            out["outage_mode"] = p.outage_mode
        if p.in_order:
            out["in_order"] = True
        return out


def _loss_to_dict(loss: LossSpec) -> dict[str, Any]:
    if isinstance(loss, RandomLoss):
        return {"model": "random", "percent": format_percent(loss.p),
                "correlation": format_percent(loss.correlation)}  # fmt: skip
    if isinstance(loss, GilbertElliott):
        return {"model": "gemodel", "p": format_percent(loss.p), "r": format_percent(loss.r),
                "1-h": format_percent(loss.one_minus_h),
                "1-k": format_percent(loss.one_minus_k)}  # fmt: skip
    return {"model": "state"} | {
        n: format_percent(getattr(loss, n)) for n in ("p13", "p31", "p32", "p23", "p14")
    }


def _parse_loss(raw: Any, corr_raw: Any, what: str) -> LossSpec | None:
    if raw is None:
        if corr_raw is not None:
            raise ConfigError(f"{what}.loss_correlation given without loss")
        return None
    if not isinstance(raw, Mapping):  # shorthand: loss = "1%" -> random loss
        p = parse_percent(raw, f"{what}.loss")
        rho = parse_percent(corr_raw, f"{what}.loss_correlation") if corr_raw is not None else 0.0
        return _model(RandomLoss, what + ".loss", p, rho) if p > 0 else None
    if corr_raw is not None:
        raise ConfigError(f"{what}: use loss.correlation inside the loss table")
    model = raw.get("model", "random")
    w = f"{what}.loss"

    def pct(name: str, default: float | None = None) -> float:
        if name not in raw:
            if default is None:
                raise ConfigError(f"{w}: {model} needs {name!r}")
            return default
        return parse_percent(raw[name], f"{w}.{name}")

    if model == "random":
        _no_unknown(raw, {"model", "percent", "correlation"}, w)
        return _model(RandomLoss, w, pct("percent"), pct("correlation", 0.0))
    if model == "gemodel":
        _no_unknown(raw, {"model", "p", "r", "1-h", "1-k"}, w)
        p = pct("p")
        return _model(GilbertElliott, w, p, pct("r", 1.0 - p), pct("1-h", 1.0), pct("1-k", 0.0))
    if model == "state":
        _no_unknown(raw, {"model", "p13", "p31", "p32", "p23", "p14"}, w)
        p13 = pct("p13")
        return _model(FourStateLoss, w, p13, pct("p31", 1.0 - p13), pct("p32", 0.0),
                      pct("p23", 1.0), pct("p14", 0.0))  # fmt: skip
    raise ConfigError(f"{w}.model must be 'random', 'gemodel' or 'state', got {model!r}")


def _model(cls: Callable[..., Any], what: str, *args: Any) -> Any:
    try:
        return cls(*args)
    except ValueError as e:
        raise ConfigError(f"{what}: {e}") from None


def _parse_outages(raw: Any, what: str, step_ms: float | None) -> tuple[Outage, ...]:
    if raw is None:
        return ()
    if isinstance(raw, Mapping):
        raw = [raw]
    if not isinstance(raw, list):
        raise ConfigError(f"{what}.outage: a table {{at, for, every}} or a list of them")
    out = []
    for i, w in enumerate(raw):
        wi = f"{what}.outage[{i}]"
        if not isinstance(w, Mapping):
            raise ConfigError(f"{wi}: expected a table with 'at', 'for' and optional 'every'")
        _no_unknown(w, {"at", "for", "every"}, wi)
        if "for" not in w:
            raise ConfigError(f"{wi}: 'for' (the duration) is required")
        start = parse_time_ns(w.get("at", 0), f"{wi}.at", step_ms)
        duration = parse_time_ns(w["for"], f"{wi}.for", step_ms)
        every = parse_time_ns(w.get("every", 0), f"{wi}.every", step_ms)
        out.append(_model(Outage, wi, start, duration, every))
    return tuple(out)


def parse_rule(raw: Any, direction: Direction, index: int, step_ms: float | None) -> Rule:
    """One rule table -> :class:`Rule` (raises :class:`ConfigError` naming the field)."""
    what = f"{direction}[{index}]"
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{what}: expected a table of netem-style fields")
    _no_unknown(raw, RULE_FIELDS, what)
    name = raw.get("name", f"{direction}-{index}")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{what}.name must be a non-empty string")
    what = f"{direction}[{index}] ({name})"
    match = check_keyexpr(raw.get("match", "**"), f"{what}.match")

    def pct(field_name: str) -> float:
        return parse_percent(raw[field_name], f"{what}.{field_name}") if field_name in raw else 0.0

    def flag(field_name: str) -> bool:
        value = raw.get(field_name, False)
        if not isinstance(value, bool):
            raise ConfigError(f"{what}.{field_name} must be true or false, got {value!r}")
        return value

    def integer(field_name: str, default: int) -> int:
        value = raw.get(field_name, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{what}.{field_name} must be an integer, got {value!r}")
        return value

    distribution = raw.get("distribution", "uniform")
    if distribution not in DISTRIBUTIONS:
        raise ConfigError(
            f"{what}.distribution must be one of {', '.join(DISTRIBUTIONS)}, got {distribution!r}"
        )
    jitter = parse_time_ns(raw.get("jitter", 0), f"{what}.jitter", step_ms)
    if "distribution" in raw and jitter == 0:
        raise ConfigError(f"{what}: distribution given without jitter")  # as tc refuses it
    delay = _model(
        DelaySpec,
        what,
        parse_time_ns(raw.get("delay", 0), f"{what}.delay", step_ms),
        jitter,
        pct("delay_correlation"),
        distribution,
    )
    if "gap" in raw and not pct("reorder"):
        raise ConfigError(f"{what}: gap given without reorder")  # as tc refuses it
    rate = None
    if "rate" in raw:
        rate = parse_rate(raw["rate"], f"{what}.rate", integer("packet_overhead", 0))
    elif "packet_overhead" in raw:
        raise ConfigError(f"{what}: packet_overhead given without rate")
    outage_mode = raw.get("outage_mode", "drop")
    if outage_mode not in ("drop", "stall"):
        raise ConfigError(f"{what}.outage_mode must be 'drop' or 'stall', got {outage_mode!r}")
    params = _model(
        LinkParams,
        what,
        delay,
        _parse_loss(raw.get("loss"), raw.get("loss_correlation"), what),
        pct("duplicate"),
        pct("duplicate_correlation"),
        pct("reorder"),
        pct("reorder_correlation"),
        integer("gap", 1),
        pct("corrupt"),
        pct("corrupt_correlation"),
        integer("corrupt_bits", 1),
        rate,
        _parse_outages(raw.get("outage"), what, step_ms),
        outage_mode,
        flag("in_order"),
    )
    return Rule(name, direction, match, params, flag("shared"))


# --- the whole configuration -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LinkConfig:
    """A parsed configuration: seed, step, key mappings and the rules of both directions."""

    seed: int = 0
    step_ms: float | None = None
    mappings: tuple[KeyMapping, ...] = DEFAULT_MAPPINGS
    downlink: tuple[Rule, ...] = ()
    uplink: tuple[Rule, ...] = ()

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
        out["downlink"] = [r.to_dict() for r in self.downlink]
        out["uplink"] = [r.to_dict() for r in self.uplink]
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


def parse_config(doc: Any, *, base: LinkConfig | None = None) -> LinkConfig:
    """A decoded document (dict) -> :class:`LinkConfig`.

    With ``base`` (runtime replacement): ``seed`` and ``step_ms`` default to the base's, and
    ``mapping`` may be omitted or must equal the base's (subscriptions are fixed at start).
    """
    if not isinstance(doc, Mapping):
        raise ConfigError("the configuration must be a table / JSON object")
    _no_unknown(doc, TOP_FIELDS, "configuration")
    seed = doc.get("seed", base.seed if base else 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"seed must be an integer, got {seed!r}")
    step_ms = doc.get("step_ms", base.step_ms if base else None)
    if step_ms is not None and (
        isinstance(step_ms, bool)
        or not isinstance(step_ms, int | float)
        or not math.isfinite(step_ms)
        or step_ms <= 0
    ):
        raise ConfigError(f"step_ms must be a number > 0, got {step_ms!r}")
    step_ms = float(step_ms) if step_ms is not None else None
    if "mapping" in doc:
        raw_maps = doc["mapping"]
        if not isinstance(raw_maps, list) or not raw_maps:
            raise ConfigError("mapping must be a non-empty list of tables")
        mappings = tuple(_parse_mapping(m, i) for i, m in enumerate(raw_maps))
        if base is not None and mappings != base.mappings:
            raise ConfigError("mapping cannot be changed at runtime; restart pd-link")
    else:
        mappings = base.mappings if base else DEFAULT_MAPPINGS
    rules: dict[str, tuple[Rule, ...]] = {}
    for direction in DIRECTIONS:
        raw_rules = doc.get(direction, [])
        if isinstance(raw_rules, Mapping):
            raw_rules = [raw_rules]
        if not isinstance(raw_rules, list):
            raise ConfigError(f"{direction} must be a list of rule tables ([[{direction}]])")
        parsed = tuple(parse_rule(r, direction, i, step_ms) for i, r in enumerate(raw_rules))
        names = [r.name for r in parsed]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ConfigError(f"{direction}: rule names must be unique, repeated: {dupes}")
        rules[direction] = parsed
    return LinkConfig(seed, step_ms, mappings, rules["downlink"], rules["uplink"])


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


def _no_unknown(raw: Mapping[str, Any], allowed: frozenset[str] | set[str], what: str) -> None:
    unknown = sorted(set(raw) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{what}: unknown field(s) {', '.join(map(repr, unknown))}; "
            f"valid: {', '.join(sorted(allowed))}"
        )
