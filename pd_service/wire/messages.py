"""Every message of the pd-service protocol, as strict pydantic v2 models.

All messages are frozen, refuse unknown fields, never coerce types (a float is not an int, a
bool is not a number), and carry the schema version ``v`` (always 1 for now). Arrays are
read-only float64 numpy arrays in Python and ``{"shape", "data"}`` maps on the wire (see
:mod:`pd_service.wire.arrays`). Integers are bounded to int64 so any language can hold them.

Units: times are integer nanoseconds on the shared clock (``*_ns``), steps are integer
indices of the session's step grid, ``step = floor((t_ns - epoch_ns) / period_ns)``;
latencies are microseconds (``*_us``); physical quantities are in whatever units the
session's model uses.

Covariances (Q, P0, R, P) must be symmetric positive semi-definite within
``PSD_RTOL = 1e-9`` relative to ``max(1, max|M|)`` (:func:`pd_service.wire.arrays.psd_problem`).

These models only check what one message can know on its own. Whether a Measurement or a
Command fits its session (sensor known, dimensions) is checked by
:func:`pd_service.wire.convert.check_measurement` / ``check_command``.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BeforeValidator,
    Discriminator,
    Field,
    PlainValidator,
    PrivateAttr,
    SerializerFunctionWrapHandler,
    StringConstraints,
    Tag,
    WithJsonSchema,
    model_serializer,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .arrays import MAX_DIM, Matrix, Vector, psd_problem
from .base import WireModel, invalid
from .keys import NAME_PATTERN
from .ros2 import Ros2Binding

SCHEMA_VERSION = 1
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1
MAX_SENSORS = 16
MAX_DELAY_LIMIT = 1000
MAX_LEAD = 10_000
MAX_TEXT = 1024
#: Bounds of a nonlinear model's parameters (``params``): entries, values in one list.
MAX_PARAMS = 32
MAX_PARAM_LIST = 256
#: Bounds of an IMM model: modes; of an adapter: window (innovations), max_gap (steps).
MIN_MODES, MAX_MODES = 2, 8
MAX_ADAPT_WINDOW = 10_000
MAX_ADAPT_GAP = 100
#: Largest lead of a nonlinear model: its predictor propagates sigma points through every
#: step of the lead at each prediction (about 70 us a step for the built-in models), where a
#: linear one uses precomputed powers of A.
MAX_NONLINEAR_LEAD = 1000
#: Tolerance on probabilities (IMM transition rows, mu0) summing to 1.
PROB_TOL = 1e-9

#: A session, sensor or instance name: ``[a-z0-9][a-z0-9_-]{0,63}``.
Name = Annotated[str, StringConstraints(pattern=f"^{NAME_PATTERN}$")]
Int64 = Annotated[int, Field(ge=INT64_MIN, le=INT64_MAX)]
NonNegInt = Annotated[int, Field(ge=0, le=INT64_MAX)]
PosInt = Annotated[int, Field(ge=1, le=INT64_MAX)]
Counters = dict[Annotated[str, StringConstraints(min_length=1, max_length=64)], Int64]
Text = Annotated[str, StringConstraints(max_length=MAX_TEXT)]
NonNegFloat = Annotated[float, Field(ge=0.0)]


def _version_is_int(value: Any) -> Any:
    # Literal[1] alone would take True and 1.0 (both == 1 in Python)
    if type(value) is not int:
        raise PydanticCustomError("wire_invalid", "Input should be 1")
    return value


class Message(WireModel):
    """A top-level message: carries the schema version ``v``."""

    v: Annotated[Literal[1], BeforeValidator(_version_is_int)] = Field(
        1, description="Schema version; always 1.")


# --- session configuration ---------------------------------------------------------------

#: What a sensor measures; see :class:`SensorSpec`.
SensorKind = Literal["linear", "model", "range_bearing", "position"]
#: Sensor kinds each model kind takes.
SENSOR_KINDS: dict[str, tuple[str, ...]] = {
    "linear": ("linear",),
    "unscented": ("model",),
    "imm": ("range_bearing", "position"),
}


class SensorSpec(WireModel):
    """One sensor group, sampled every ``interval`` steps, noise v ~ N(0, R).

    ``kind`` says what the sensor measures (m = rows of R for every kind):

    - ``"linear"`` (default): z = H x(s) + v, H is m x n (linear models);
    - ``"model"``: z = h(x(s)) + v, h the sensor of this ``name`` in the registered model
      (unscented models); R replaces the model's R for this sensor;
    - ``"range_bearing"``: z = [range (m), bearing (rad)] of the target seen from
      ``station`` (IMM models); R = diag(sigma_range^2, sigma_bearing^2);
    - ``"position"``: z = [xi, eta] (m) (IMM models); R 2 x 2 positive definite.

    Rules: H is given iff kind is "linear" (then R is m x m, m = rows of H); station is
    given iff kind is "range_bearing"; R symmetric PSD. On the wire ``kind``, ``H`` and
    ``station`` are written only where they apply, so a linear sensor is encoded byte for
    byte as before these kinds existed (and older readers still take it).
    """

    name: Name = Field(description="Sensor name, unique in the session; the sensor key's last chunk.")
    H: Matrix | None = Field(
        None, description="Observation matrix, m x n; required for kind 'linear', absent otherwise.")
    R: Matrix = Field(description="Measurement noise covariance, m x m, symmetric PSD.")
    delay: Annotated[int, Field(ge=0, le=MAX_DELAY_LIMIT)] = Field(
        description="Nominal downlink delay in steps (0..max_delay).")
    interval: PosInt = Field(description="Sample interval in steps (1 = every step).")
    kind: SensorKind = Field(
        "linear", description="What the sensor measures: 'linear' (z = H x, default), 'model' "
                              "(the unscented model's sensor of this name), 'range_bearing' "
                              "or 'position' (IMM).")
    station: Vector | None = Field(
        None, description="Station position (xi, eta), m; required for kind 'range_bearing', "
                          "absent otherwise.")

    @property
    def m(self) -> int:
        """Measurement dimension (rows of R)."""
        return int(self.R.shape[0])

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out = handler(self)
        if self.kind == "linear":
            out.pop("kind", None)
        if self.H is None:
            out.pop("H", None)
        if self.station is None:
            out.pop("station", None)
        return out

    @model_validator(mode="after")
    def _check(self) -> SensorSpec:
        kind = self.kind
        if kind == "linear":
            if self.H is None:
                raise invalid("H", "is required for a sensor of kind 'linear' (z = H x + v)")
            m = self.H.shape[0]
            if self.R.shape != (m, m):
                raise invalid("R", f"must be {m}x{m} (H has {m} rows), got shape {list(self.R.shape)}")
        elif self.H is not None:
            raise invalid("H", f"is only for kind 'linear'; a {kind!r} sensor's h(x) is the model's")
        if kind == "range_bearing":
            if self.station is None:
                raise invalid("station", "is required for kind 'range_bearing'")
            if self.station.shape != (2,):
                raise invalid("station", f"must have 2 values (xi, eta), got {self.station.shape[0]}")
        elif self.station is not None:
            raise invalid("station", f"is only for kind 'range_bearing', not {kind!r}")
        problem = psd_problem(self.R)
        if problem:
            raise invalid("R", problem)
        if kind in ("range_bearing", "position"):
            R = self.R
            if R.shape != (2, 2):
                raise invalid("R", f"must be 2x2 for kind {kind!r} (z has 2 values), "
                               f"got shape {list(R.shape)}")
            if kind == "range_bearing" and not (R[0, 1] == 0.0 == R[1, 0] and R[0, 0] > 0.0
                                                and R[1, 1] > 0.0):
                raise invalid("R", "must be diagonal with positive entries for kind "
                               "'range_bearing': diag(sigma_range^2, sigma_bearing^2)")
            if kind == "position" and not float(np.linalg.eigvalsh(0.5 * (R + R.T))[0]) > 0.0:
                raise invalid("R", "must be positive definite for kind 'position' "
                               "(the IMM filter uses R^-1)")
        return self


class LinearModelSpec(WireModel):
    """Linear time-invariant model, discrete or continuous in time.

    Discrete (A, B, Q): x(k+1) = A x(k) + B u(k) + w(k), w ~ N(0, Q), per step; samples and
    commands act on the step grid (stamps rounded: SessionSpec.stamp_rounding).
    Continuous (F, G, Qc; t in seconds): dx = (F x + G u) dt + dw, E[dw dw^T] = Qc dt; the
    daemon discretises it exactly over any interval, so a sample and a command act at their
    own time inside a step (docs/protocol.md, "When a sample and a command apply").

    Rules: exactly one of the triples (A, B, Q) / (F, G, Qc), complete. A / F is n x n;
    B / G is n x r (r >= 1); Q / Qc is n x n, symmetric PSD.
    """

    kind: Literal["linear"] = Field("linear", description="Model kind (discriminator).")
    A: Matrix | None = Field(None, description="State transition per step, n x n (n <= 64). "
                                               "Discrete models.")
    B: Matrix | None = Field(None, description="Input matrix per step, n x r (r = command "
                                               "dimension). Discrete models.")
    Q: Matrix | None = Field(None, description="Process noise covariance per step, n x n, "
                                               "symmetric PSD. Discrete models.")
    F: Matrix | None = Field(None, description="Continuous-time state matrix, n x n, 1/s. "
                                               "Continuous models.")
    G: Matrix | None = Field(None, description="Continuous-time input matrix, n x r. "
                                               "Continuous models.")
    Qc: Matrix | None = Field(None, description="Process noise spectral density, n x n, "
                                                "symmetric PSD, (units of x)^2 / s. "
                                                "Continuous models.")

    @property
    def continuous(self) -> bool:
        """Whether the model is given in continuous time (F, G, Qc)."""
        return self.F is not None

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The given triple: (F, G, Qc) of a continuous model, else (A, B, Q)."""
        got = (self.F, self.G, self.Qc) if self.F is not None else (self.A, self.B, self.Q)
        assert got[0] is not None and got[1] is not None and got[2] is not None  # _check
        return got[0], got[1], got[2]

    @property
    def n(self) -> int:
        """State dimension."""
        return int(self.matrices()[0].shape[0])

    @property
    def r(self) -> int:
        """Command (input) dimension."""
        return int(self.matrices()[1].shape[1])

    @model_validator(mode="after")
    def _check(self) -> LinearModelSpec:
        disc, cont = (self.A, self.B, self.Q), (self.F, self.G, self.Qc)
        given = [x is not None for x in disc + cont]
        if given != [True] * 3 + [False] * 3 and given != [False] * 3 + [True] * 3:
            raise invalid("A", "give exactly one complete model: A, B, Q (discrete) or F, G, "
                               "Qc (continuous)")
        names = ("A", "B", "Q") if self.A is not None else ("F", "G", "Qc")
        T, In, N = self.matrices()
        n = T.shape[0]
        if T.shape != (n, n):
            raise invalid(names[0], f"must be square (n x n), got shape {list(T.shape)}")
        if In.shape[0] != n:
            raise invalid(names[1], f"must have n={n} rows ({names[0]} is {n}x{n}), got shape "
                                    f"{list(In.shape)}")
        if N.shape != (n, n):
            raise invalid(names[2], f"must be {n}x{n} ({names[0]} is {n}x{n}), got shape "
                                    f"{list(N.shape)}")
        problem = psd_problem(N)
        if problem:
            raise invalid(names[2], problem)
        return self

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out = handler(self)
        for k in ("A", "B", "Q", "F", "G", "Qc"):  # the other triple: absent, not nil
            if out.get(k, 0) is None:
                out.pop(k)
        return out


# --- nonlinear models: registered names and their parameters ----------------------------

_PARAM_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")


def _param_number(value: Any, where: str) -> int | float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise invalid(where, "expected a number or a list of numbers, got "
                       f"{'nil' if value is None else type(value).__name__}")
    if isinstance(value, int | np.integer):
        v = int(value)
        if not INT64_MIN <= v <= INT64_MAX:
            raise invalid(where, f"integer {v} is outside int64")
        return v
    f = float(value)
    if not math.isfinite(f):
        raise invalid(where, "must be a finite number (no NaN or infinity)")
    return f


def _params(value: Any) -> dict[str, int | float | list[int | float]]:
    """A model's parameters: name -> finite number or list of 1..256 finite numbers."""
    if not isinstance(value, dict):
        raise invalid("", "must be a map: parameter name -> number or list of numbers")
    if len(value) > MAX_PARAMS:
        raise invalid("", f"at most {MAX_PARAMS} entries, got {len(value)}")
    out: dict[str, int | float | list[int | float]] = {}
    for key, v in value.items():
        if type(key) is not str or not _PARAM_NAME.match(key):
            raise invalid("", f"{str(key)[:70]!r} is not a parameter name "
                           "([A-Za-z_][A-Za-z0-9_]{0,63})")
        where = key
        if isinstance(v, list | tuple) or (isinstance(v, np.ndarray) and v.ndim == 1):
            if not 1 <= len(v) <= MAX_PARAM_LIST:
                raise invalid(where, f"a list holds 1..{MAX_PARAM_LIST} numbers, got {len(v)}")
            out[key] = [_param_number(x, where) for x in v]
        else:
            out[key] = _param_number(v, where)
    return out


#: Parameters of a registered model: ``{name: number | [numbers]}`` (at most 32 entries,
#: lists of 1..256 finite numbers; ints stay ints). Which names a model takes is the
#: model's business: a wrong one is refused when the daemon builds the model.
Params = Annotated[
    dict[str, Any],
    PlainValidator(_params),
    WithJsonSchema({
        "type": "object",
        "description": "Model parameters: name -> finite number or list of finite numbers.",
        "maxProperties": MAX_PARAMS,
        "propertyNames": {"pattern": _PARAM_NAME.pattern},
        "additionalProperties": {"anyOf": [
            {"type": "number"},
            {"type": "array", "minItems": 1, "maxItems": MAX_PARAM_LIST,
             "items": {"type": "number"}},
        ]},
    }),
]

Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class AdaptSpec(WireModel):
    """Online adaptation of chosen diagonal entries q_m of Q (unscented models).

    ``"mit"``: MIT rule on the windowed innovation-covariance mismatch; ``"sage_husa"``:
    Sage-Husa covariance matching. Absent settings take the backend's defaults (mit: window
    50, eta 0.1, rule "normalised", clip 0.1, max_gap 4; sage_husa: forgetting 0.98; bounds
    q0 * 1e-4 .. q0 * 1e4). Rules: indices distinct and < n; mit-only settings (window, eta,
    rule, clip, max_gap) not with sage_husa, forgetting not with mit; q_min / q_max one value
    per index, 0 < q_min <= q_max. The adapted entries of the model's Q must be > 0 (checked
    when the model is built).
    """

    method: Literal["mit", "sage_husa"] = Field("mit", description="Adaptation rule.")
    indices: Annotated[list[Annotated[int, Field(ge=0, lt=MAX_DIM)]],
                       Field(min_length=1, max_length=MAX_DIM)] = Field(
        description="State indices m of the adapted diagonal entries Q[m, m] (normally the "
                    "acceleration channels).")
    window: Annotated[int, Field(ge=1, le=MAX_ADAPT_WINDOW)] | None = Field(
        None, description="mit: innovations per window, N.")
    eta: Annotated[float, Field(gt=0.0)] | None = Field(None, description="mit: adaptation rate.")
    rule: Literal["normalised", "plain"] | None = Field(
        None, description="mit: 'normalised' (unit-free step in log q) or 'plain' gradient step.")
    clip: Annotated[float, Field(gt=0.0)] | None = Field(
        None, description="mit: bound on one step of log q.")
    max_gap: Annotated[int, Field(ge=1, le=MAX_ADAPT_GAP)] | None = Field(
        None, description="mit: longest gap (steps since the previous update) whose "
                          "innovations are used.")
    forgetting: Annotated[float, Field(gt=0.0, lt=1.0)] | None = Field(
        None, description="sage_husa: forgetting factor b in (0, 1).")
    q_min: Annotated[list[Annotated[float, Field(gt=0.0)]],
                     Field(min_length=1, max_length=MAX_DIM)] | None = Field(
        None, description="Lower bounds of the adapted q, one per index.")
    q_max: Annotated[list[Annotated[float, Field(gt=0.0)]],
                     Field(min_length=1, max_length=MAX_DIM)] | None = Field(
        None, description="Upper bounds of the adapted q, one per index.")

    @model_validator(mode="after")
    def _check(self) -> AdaptSpec:
        if len(set(self.indices)) != len(self.indices):
            raise invalid("indices", f"must be distinct, got {self.indices}")
        only = {"mit": ("forgetting",), "sage_husa": ("window", "eta", "rule", "clip", "max_gap")}
        wrong = [k for k in only[self.method] if getattr(self, k) is not None]
        if wrong:
            raise invalid(wrong[0], f"{', '.join(wrong)} {'does' if len(wrong) == 1 else 'do'} not "
                                     f"apply to method {self.method!r}")
        p = len(self.indices)
        for key in ("q_min", "q_max"):
            v = getattr(self, key)
            if v is not None and len(v) != p:
                raise invalid(key, f"must have one value per index ({p}), got {len(v)}")
        if self.q_min is not None and self.q_max is not None and \
                any(lo > hi for lo, hi in zip(self.q_min, self.q_max, strict=True)):
            raise invalid("q_min", "must be <= q_max")
        return self


class SigmaSpec(WireModel):
    """Scaled sigma points: lambda = alpha^2 (n + kappa) - n. Rule: n + kappa > 0."""

    alpha: Annotated[float, Field(gt=0.0)] = Field(1.0, description="Spread, > 0.")
    beta: float = Field(2.0, description="Prior knowledge of the distribution (2 for Gaussian).")
    kappa: float = Field(0.0, description="Secondary scaling.")


class UnscentedModelSpec(WireModel):
    """A registered nonlinear model x(k+1) = f(x, u, k) + w, z_i = h_i(x) + v_i, estimated by
    the unscented observer-predictor, optionally with adaptive process noise.

    n is the length of the session's x0 and must be the built model's; r (command
    dimension) is the model's. The session's sensors are of kind "model": each names one of
    the model's sensors and its R replaces the model's. Which models exist and which
    parameters they take is known only to the daemon (a wrong name, parameter or dimension
    is refused when the session is built, with the reason).
    """

    kind: Literal["unscented"] = Field("unscented", description="Model kind (discriminator).")
    model: Name = Field(description="Registered model name, e.g. 'omni3'.")
    params: Params = Field(default_factory=dict, description="The model's parameters.")
    adapt: AdaptSpec | None = Field(None, description="Process-noise adaptation; nil = none.")
    sigma: SigmaSpec | None = Field(
        None, description="Sigma-point scaling; nil = alpha 1, beta 2, kappa 0.")


class ModeSpec(WireModel):
    """One IMM mode: a registered model and its parameters (e.g. 'imm_cv', 'imm_ct')."""

    model: Name = Field(description="Registered model name.")
    params: Params = Field(default_factory=dict, description="The model's parameters.")


class ImmModelSpec(WireModel):
    """Interacting multiple models of unscented information filters, fusing several sensors.

    Rules: transition is r x r (r = number of modes), entries >= 0, every row sums to 1
    within 1e-9 (row i = P(next mode | mode i)); mu0, if given, has r values >= 0 summing to
    1 within 1e-9 (nil = uniform); node < number of sensors; n + kappa > 0. Every mode has the
    same state (n = length of x0) and input dimension; the sensors are of kind
    "range_bearing" or "position".
    """

    kind: Literal["imm"] = Field("imm", description="Model kind (discriminator).")
    modes: Annotated[list[ModeSpec], Field(min_length=MIN_MODES, max_length=MAX_MODES)] = Field(
        description="The modes (2..8).")
    transition: Matrix = Field(description="Markov transition matrix, r x r, row-stochastic.")
    variant: Literal["single", "centralised", "imm1", "imm2"] = Field(
        description="'single' (sensor `node` only), 'centralised' (joint likelihood), 'imm1' "
                    "(one IMM per sensor node, node `node` reported), 'imm2' (likelihoods "
                    "fused across sensors).")
    node: Annotated[int, Field(ge=0, lt=MAX_SENSORS)] = Field(
        0, description="Index into sensors: the sensor of 'single', the reported node of 'imm1'.")
    mu0: Vector | None = Field(None, description="Initial mode probabilities, r; nil = uniform.")
    kappa: float = Field(0.0, description="Sigma-point scaling (n + kappa > 0).")

    @model_validator(mode="after")
    def _check(self) -> ImmModelSpec:
        r = len(self.modes)
        T = self.transition
        if T.shape != (r, r):
            raise invalid("transition", f"must be {r}x{r} ({r} modes), got shape {list(T.shape)}")
        if (T < 0.0).any():
            raise invalid("transition", "entries must be >= 0")
        worst = float(np.abs(T.sum(axis=1) - 1.0).max())
        if worst > PROB_TOL:
            raise invalid("transition", f"every row must sum to 1 (off by {worst:.3g})")
        if self.mu0 is not None:
            mu = self.mu0
            if mu.shape != (r,):
                raise invalid("mu0", f"must have {r} values ({r} modes), got {mu.shape[0]}")
            if (mu < 0.0).any() or abs(float(mu.sum()) - 1.0) > PROB_TOL:
                raise invalid("mu0", "must be >= 0 and sum to 1")
        return self


def _model_kind(value: Any) -> str | None:
    if isinstance(value, dict):
        kind = value.get("kind", "linear")
        return kind if isinstance(kind, str) else None
    return getattr(value, "kind", None)


#: Every model kind, discriminated by ``kind`` (absent means "linear"). A new kind is one
#: more ``Annotated[NewModelSpec, Tag("new")]`` here, plus its case in
#: ``pd_service.backends.build`` (its nu, cost and estimator).
ModelSpec = Annotated[
    Annotated[LinearModelSpec, Tag("linear")]
    | Annotated[UnscentedModelSpec, Tag("unscented")]
    | Annotated[ImmModelSpec, Tag("imm")],
    Discriminator(
        _model_kind,
        custom_error_type="wire_model_kind",
        custom_error_message="model must be a map whose 'kind' is one of: linear, unscented, imm",
    ),
]


#: Most points a PredictedPath carries: the daemon widens the stride to stay within it.
MAX_PATH_POINTS = 64
#: Most state components a PredictedPath carries (its P blocks are d x d).
MAX_PATH_COMPONENTS = 8


class PathSpec(WireModel):
    """Publish the predicted path with the predictions (``pd/p<k>/<session>/path``, a
    PredictedPath): the predicted states from the newest measured step to now + lead, of the
    components ``indices`` only. Off unless given: without it nothing changes."""

    indices: Annotated[list[Annotated[int, Field(ge=0, le=MAX_DIM - 1)]],
                       Field(min_length=1, max_length=MAX_PATH_COMPONENTS)] = Field(
        description="State components carried (1..8 distinct, each < n), e.g. the positions "
                    "[0, 2]; the path's P blocks are their covariance.")
    every: PosInt = Field(1, description="A path with every this-many-th published Prediction "
                                         "(rate bound: at most one per Prediction).")
    stride: PosInt = Field(1, description="Steps between points (the first and the target "
                                          "always included); widened by the daemon so that "
                                          "a path has at most 64 points.")

    @model_validator(mode="after")
    def _check_path(self) -> PathSpec:
        if len(set(self.indices)) != len(self.indices):
            raise invalid("indices", f"{self.indices} repeats a component")
        return self


class SessionSpec(Message):
    """Creates or replaces a session (put on ``pd/p<k>/<session>/config``).

    Rules: n = state dimension (1..64): the rows of model.A for a linear model, the length
    of x0 otherwise; x0 has n values; P0 is n x n; sensor names are unique; every sensor
    delay <= max_delay; sensor kinds fit the model kind (linear: "linear", every H with n
    columns; unscented: "model"; imm: "range_bearing" / "position"); covariances symmetric
    PSD (tolerance 1e-9 * max(1, max|M|)); for nonlinear models lead <= 1000,
    adapt.indices < n, n + kappa > 0 and imm node < number of sensors.
    """

    session: Name = Field(description="Session id.")
    period_ns: PosInt = Field(description="Step period, ns.")
    epoch_ns: Int64 = Field(description="Time of step 0 on the shared clock, ns.")
    model: ModelSpec = Field(description="System model; 'kind' selects the model type.")
    x0: Vector = Field(description="Prior mean of x(0), n.")
    P0: Matrix = Field(description="Prior covariance of x(0), n x n, symmetric PSD.")
    sensors: Annotated[list[SensorSpec], Field(min_length=1, max_length=MAX_SENSORS)] = Field(
        description="Sensor groups (1..16, unique names).")
    lead: Annotated[int, Field(ge=0, le=MAX_LEAD)] = Field(
        description="Prediction lead, steps: the uplink delay plus the shift the observer "
                    "moves there. Predictions target now + lead.")
    max_delay: Annotated[int, Field(ge=0, le=MAX_DELAY_LIMIT)] = Field(
        description="Oldest accepted sample, steps: a sample stamped s is accepted at step "
                    "now iff now - max_delay <= s <= now.")
    publish_every: PosInt = Field(1, description="Publish a Prediction every this many steps.")
    command_hold: Literal["hold", "zero"] = Field(
        "hold", description="A step without a command: hold the last u, or use u = 0.")
    stamp_rounding: Literal["floor", "nearest"] = Field(
        "nearest", description="Discrete linear models only: a t_ns stamp goes to the step "
                               "that contains it ('floor') or to the nearest step start "
                               "('nearest'; never past the current step). Default 'nearest': "
                               "the smaller error (docs/protocol.md). Continuous models apply "
                               "every sample at its own time.")
    ros2: Ros2Binding | None = Field(
        None, description="ROS 2 topics of the session (served by the pd-ros2 bridge).")
    robot_clock: Literal["shared", "estimated"] = Field(
        "shared", description="shared: robot stamps are on the daemon's clock (NTP/PTP); "
        "estimated: the daemon estimates the robot clock's offset (probes, echoes, one-way "
        "stamps) and maps every robot stamp to its own timeline before the window check.")
    command_timing: Literal["stamped", "echoed"] = Field(
        "stamped", description="stamped: a command applies at its stamped apply step; "
        "echoed: it moves to the instant the robot's CommandEcho says it took effect (inside "
        "the step for a continuous-time model); until then, or if no echo comes, it applies at "
        "its stamped instant.")
    clock_asymmetry_ns: Annotated[int, Field(ge=-60 * 10**9, le=60 * 10**9)] = Field(
        0, description="robot_clock 'estimated' only: the link's fastest uplink delay minus its "
        "fastest downlink delay, ns (500 ms up, 600 ms down: -100000000), the part of the "
        "offset no timestamp shows (the estimate is off by half of it unless given); 0: "
        "symmetric.")
    path: PathSpec | None = Field(
        None, description="Publish the predicted path too (docs/protocol.md); absent: never.")
    expire_s: Annotated[float, Field(ge=0.0, le=1e9, allow_inf_nan=False)] | None = Field(
        None, description="Seconds without a measurement or command after which the service "
                          "removes the session (state expired); 0: never; absent: the "
                          "service's expire_s setting (120 s by default).")

    # name -> SensorSpec, rebuilt whenever `sensors` is not the list it was built from
    # (model_copy(update=...) copies private attributes but not their meaning).
    _sensor_index: dict[str, SensorSpec] = PrivateAttr(default_factory=dict)
    _sensor_index_of: list[SensorSpec] | None = PrivateAttr(default=None)

    @property
    def n(self) -> int:
        """State dimension (the length of x0; for a linear model also the rows of A)."""
        return int(self.x0.shape[0])

    @property
    def r(self) -> int | None:
        """Command (input) dimension of a linear model; None for the other kinds, whose
        registered model knows it (:func:`pd_service.backends.command_dim`)."""
        return self.model.r if isinstance(self.model, LinearModelSpec) else None

    def sensor(self, name: str) -> SensorSpec | None:
        """The sensor called ``name``, or None."""
        if self._sensor_index_of is not self.sensors:
            self._sensor_index = {s.name: s for s in self.sensors}
            self._sensor_index_of = self.sensors
        return self._sensor_index.get(name)

    def step_of(self, t_ns: int) -> int:
        """Step containing time ``t_ns``: floor((t_ns - epoch_ns) / period_ns), exact."""
        return (t_ns - self.epoch_ns) // self.period_ns

    @property
    def continuous_time(self) -> bool:
        """Whether samples and commands act at their own time inside a step: a linear
        model given in continuous time (F, G, Qc), or a nonlinear model (its f integrates
        over any interval)."""
        model = self.model
        return model.continuous if isinstance(model, LinearModelSpec) else True

    def sample_at(self, t_ns: int) -> tuple[int, float]:
        """(step, offset in s) at which a sample taken at ``t_ns`` is applied.

        Continuous time: the step containing it and the exact offset into it,
        ``(t_ns - epoch_ns - step * period_ns) / 1e9`` (0 <= offset < period). Otherwise
        offset 0.0 and the step by :attr:`stamp_rounding`: floor((t_ns - epoch_ns) /
        period_ns), or floor((t_ns - epoch_ns + period_ns / 2) / period_ns) ("nearest"; the
        caller keeps it from passing the current step)."""
        rel = t_ns - self.epoch_ns
        if self.continuous_time:
            step = rel // self.period_ns
            return step, (rel - step * self.period_ns) / 1e9
        if self.stamp_rounding == "nearest":
            return (rel + self.period_ns // 2) // self.period_ns, 0.0
        return rel // self.period_ns, 0.0

    def command_at(self, issued_ns: int) -> tuple[int, float]:
        """(apply step, offset in s) of a command issued at ``issued_ns``: it acts ``lead``
        steps later, ``step_of(issued_ns) + lead``; continuous time: at exactly issued_ns +
        lead * period_ns (the same offset into its step), otherwise at the step's start."""
        rel = issued_ns - self.epoch_ns
        step = rel // self.period_ns
        off = (rel - step * self.period_ns) / 1e9 if self.continuous_time else 0.0
        return step + self.lead, off

    def time_of(self, step: int) -> int:
        """Start time of ``step`` in ns: epoch_ns + step * period_ns."""
        return self.epoch_ns + step * self.period_ns

    @model_validator(mode="after")
    def _check(self) -> SessionSpec:
        model = self.model
        if isinstance(model, LinearModelSpec):
            n = model.n
            if n > MAX_DIM:  # unreachable while MAX_DIM bounds every array axis; kept explicit
                raise invalid("model.linear.A", f"state dimension n={n} exceeds {MAX_DIM}")
            source = f"model.{'F' if model.continuous else 'A'} is {n}x{n}"
            if self.x0.shape != (n,):
                raise invalid("x0", f"must have n={n} values ({source}), "
                               f"got {self.x0.shape[0]}")
        else:
            n = self.x0.shape[0]
            source = f"x0 has {n} values"
            if self.lead > MAX_NONLINEAR_LEAD:
                raise invalid("lead", f"{self.lead} exceeds {MAX_NONLINEAR_LEAD} for a "
                               f"{model.kind!r} model (every step of lead is propagated "
                               "at each prediction)")
        if self.P0.shape != (n, n):
            raise invalid("P0", f"must be {n}x{n} ({source}), got shape {list(self.P0.shape)}")
        problem = psd_problem(self.P0)
        if problem:
            raise invalid("P0", problem)
        if self.path is not None and max(self.path.indices) >= n:
            raise invalid("path.indices", f"{self.path.indices} must be < n={n} ({source})")
        allowed = SENSOR_KINDS[model.kind]
        seen: set[str] = set()
        for i, s in enumerate(self.sensors):
            if s.name in seen:
                raise invalid(f"sensors.{i}.name", f"{s.name!r} is used twice; names must be unique")
            seen.add(s.name)
            if s.kind not in allowed:
                raise invalid(f"sensors.{i}.kind", f"{s.kind!r} ({s.name!r}) does not fit a "
                               f"{model.kind!r} model (use: {', '.join(allowed)})")
            if s.H is not None and s.H.shape[1] != n:
                raise invalid(f"sensors.{i}.H", f"must have n={n} columns ({s.name!r}), "
                               f"got shape {list(s.H.shape)}")
            if s.delay > self.max_delay:
                raise invalid(f"sensors.{i}.delay", f"{s.delay} ({s.name!r}) exceeds "
                               f"max_delay={self.max_delay}: every sample would be late")
        if isinstance(model, UnscentedModelSpec):
            if model.adapt is not None and max(model.adapt.indices) >= n:
                raise invalid("model.unscented.adapt.indices", f"{model.adapt.indices} must be < n={n} "
                               f"({source})")
            if model.sigma is not None and not n + model.sigma.kappa > 0:
                raise invalid("model.unscented.sigma.kappa", f"n + kappa must be > 0 (n={n}, "
                               f"kappa={model.sigma.kappa})")
        elif isinstance(model, ImmModelSpec):
            if model.node >= len(self.sensors):
                raise invalid("model.imm.node", f"{model.node} must index one of the "
                               f"{len(self.sensors)} sensors")
            if not n + model.kappa > 0:
                raise invalid("model.imm.kappa", f"n + kappa must be > 0 (n={n}, kappa={model.kappa})")
        if self.ros2 is not None:
            self._check_ros2(self.ros2, n)
        return self

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out = handler(self)
        if self.ros2 is None:  # a session without ROS 2 topics: the bytes stay as before
            out.pop("ros2", None)
        if self.robot_clock == "shared":  # the defaults: the bytes (and fingerprints) as before
            out.pop("robot_clock", None)
        if self.command_timing == "stamped":
            out.pop("command_timing", None)
        if self.clock_asymmetry_ns == 0:
            out.pop("clock_asymmetry_ns", None)
        if self.expire_s is None:  # the service's lifetime: the bytes stay as before
            out.pop("expire_s", None)
        if self.stamp_rounding == "nearest":  # the default: the bytes stay as before
            out.pop("stamp_rounding", None)
        if self.path is None:  # no path (the default): the bytes stay as before
            out.pop("path", None)
        return out

    def _check_ros2(self, ros2: Ros2Binding, n: int) -> None:
        for name, binding in ros2.sensors.items():
            sensor = self.sensor(name)
            if sensor is None:
                raise invalid(f"ros2.sensors.{name}", "no sensor of that name in sensors")
            m = sensor.H.shape[0] if sensor.H is not None else None
            if m is not None and m != len(binding.fields):
                raise invalid(f"ros2.sensors.{name}.fields", f"has {len(binding.fields)} "
                               f"values but sensor {name!r} measures m={m}")
        if ros2.outputs is not None:
            for quantity, i in ros2.outputs.layout.indices().items():
                if i >= n:
                    raise invalid(f"ros2.outputs.layout.{quantity}", f"{i} must be < n={n}")
            lay = ros2.outputs.layout
            if self.path is not None and ros2.outputs.path_topic is not None and (
                    lay.x is None or lay.y is None
                    or not {lay.x, lay.y} <= set(self.path.indices)):
                raise invalid("path.indices", f"{self.path.indices} must hold the ROS 2 "
                               f"layout's x ({lay.x}) and y ({lay.y}): its nav_msgs/Path "
                               "carries them (or set ros2.outputs.path_topic to null)")


# --- streams into the daemon ------------------------------------------------------------

class Measurement(Message):
    """One sensor sample (``pd/p<k>/<session>/sensor/<name>``): z = H x(s) + v (or h(x(s)) + v).

    Rules: exactly one of step / t_ns; R, if given, is m x m (m = len(z)) symmetric PSD.
    Against the session: the sensor exists and z has its dimension m (rows of its R).
    """

    session: Name = Field(description="Session id.")
    sensor: Name = Field(description="Sensor name, as in the SessionSpec.")
    seq: NonNegInt = Field(description="Sender's sequence number (per sensor), for reports.")
    step: NonNegInt | None = Field(None, description="Sample step s. Exactly one of step / t_ns.")
    t_ns: Int64 | None = Field(
        None, description="Sample time, ns on the shared clock (full resolution); s = "
                          "floor((t_ns - epoch_ns) / period_ns), applied at exactly t_ns for a "
                          "continuous-time model, at a step start for a discrete one "
                          "(SessionSpec.stamp_rounding). Exactly one of step / t_ns.")
    z: Vector = Field(description="Measured values, m.")
    R: Matrix | None = Field(
        None, description="Noise covariance of this sample only, m x m, symmetric PSD; "
                          "absent = the sensor's R.")

    @model_validator(mode="after")
    def _check(self) -> Measurement:
        if (self.step is None) == (self.t_ns is None):
            raise invalid("step", "exactly one of step / t_ns must be given"
                           + (", got both" if self.step is not None else ", got neither"))
        if self.R is not None:
            m = self.z.shape[0]
            if self.R.shape != (m, m):
                raise invalid("R", f"must be {m}x{m} (z has {m} values), got shape {list(self.R.shape)}")
            problem = psd_problem(self.R)
            if problem:
                raise invalid("R", problem)
        return self


class Command(Message):
    """One operator command (``pd/p<k>/<session>/cmd``): u applies from its apply step on.

    Rules: exactly one of step / issued_ns. Against the session: u has r values (the
    columns of model.B, or the registered model's input dimension).
    """

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Sender's sequence number, for reports.")
    step: NonNegInt | None = Field(
        None, description="Apply step: u acts from this step on. Exactly one of step / issued_ns.")
    issued_ns: Int64 | None = Field(
        None, description="Time the operator issued it, ns; apply step = "
                          "floor((issued_ns - epoch_ns) / period_ns) + lead, acting from "
                          "exactly issued_ns + lead * period_ns for a continuous-time model. "
                          "Exactly one of step / issued_ns.")
    u: Vector = Field(description="Command, r values.")

    @model_validator(mode="after")
    def _check(self) -> Command:
        if (self.step is None) == (self.issued_ns is None):
            raise invalid("step", "exactly one of step / issued_ns must be given"
                           + (", got both" if self.step is not None else ", got neither"))
        return self


# --- the robot's side: echoes and clock probes (issue 43) ---------------------------------

class CommandEcho(Message):
    """When a command took effect on the robot (``robot/p<k>/<session>/echo``, bridged to
    ``pd/p<k>/<session>/echo`` like a sensor), on the *robot's* clock: the daemon maps it to
    its own timeline with the session's clock-offset estimate."""

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="seq of the Command that took effect.")
    applied_ns: Int64 = Field(description="When it took effect, ns on the robot's clock.")
    sent_ns: Int64 | None = Field(
        None, description="When this echo was sent, ns on the robot's clock (a one-way stamp "
                          "for the offset estimate); nil: not given.")


class ClockProbe(Message):
    """A time probe: the payload of a query on the robot's ``robot/p<k>/<session>/clock``
    queryable (the daemon asks at a bounded rate). ``t1_ns``: when it was sent, ns on the
    sender's clock, echoed in the reply."""

    session: Name = Field(description="Session id.")
    probe: NonNegInt = Field(description="Sender's probe number, echoed in the reply.")
    t1_ns: Int64 = Field(description="When the probe was sent, ns on the sender's clock.")


class ClockProbeReply(Message):
    """The robot's answer to a :class:`ClockProbe`: with the sender's receipt time t4 the four
    timestamps of an NTP-style exchange (t1, t4 sender's clock; t2, t3 robot's clock).

    Rules: t3_ns >= t2_ns."""

    session: Name = Field(description="Session id.")
    probe: NonNegInt = Field(description="The probe's number.")
    t1_ns: Int64 = Field(description="The probe's t1_ns, echoed.")
    t2_ns: Int64 = Field(description="When the robot received the probe, ns on its clock.")
    t3_ns: Int64 = Field(description="When the robot answered, ns on its clock.")

    @model_validator(mode="after")
    def _check(self) -> ClockProbeReply:
        if self.t3_ns < self.t2_ns:
            raise invalid("t3_ns", f"must be >= t2_ns ({self.t2_ns}), got {self.t3_ns}")
        return self


# --- streams out of the daemon ----------------------------------------------------------

class Prediction(Message):
    """The predicted state at a target step (``pd/p<k>/<session>/prediction``).

    Rules: P is n x n (n = len(x)), symmetric PSD.
    """

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Publisher's sequence number (per session).")
    step: NonNegInt = Field(description="Target step (the step at which a command sent now acts).")
    t_ns: Int64 = Field(description="Start time of the target step, ns: epoch_ns + step * period_ns.")
    x: Vector = Field(description="Predicted state mean, n.")
    P: Matrix = Field(description="Predicted state covariance, n x n, symmetric PSD.")
    newest_step: NonNegInt | None = Field(
        None, description="Newest sample step among the measurements used; nil before any.")
    made_ns: Int64 = Field(description="When the prediction was computed, ns on the shared clock.")
    counters: Counters = Field(default_factory=dict,
                               description="Session counters (accepted, refused by reason, ...).")
    term: NonNegInt = Field(
        0, description="Ownership term of the publisher: grows with each takeover and "
        "hand-over of the session; a reader drops a prediction of an older term than the "
        "newest it saw for the session (absent: 0, a publisher older than terms).")

    @model_validator(mode="after")
    def _check(self) -> Prediction:
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise invalid("P", f"must be {n}x{n} (x has {n} values), got shape {list(self.P.shape)}")
        problem = psd_problem(self.P)
        if problem:
            raise invalid("P", problem)
        return self


#: How the reason of an ErrorReport that refuses a config change by the service's rate
#: limits begins (``config_rate_limited: config change refused: ...``): the change was not
#: judged, so a client may send it again a little later (the SDK's Admin does).
CONFIG_RATE_LIMITED = "config_rate_limited"


class ErrorReport(Message):
    """Why a message was refused (``pd/p<k>/<session>/error``, rate-limited by the daemon)."""

    session: Name = Field(description="Session id.")
    key: Annotated[str, StringConstraints(max_length=512)] = Field(
        description="Key expression the refused message arrived on.")
    seq: NonNegInt | None = Field(None, description="seq of the refused message, if it could be read.")
    reason: Text = Field(description="Why it was refused, one readable line.")
    t_ns: Int64 = Field(description="When it was refused, ns on the shared clock.")


class ClockStatus(WireModel):
    """A session's robot clock as the daemon estimates it (``SessionStatus.clock``)."""

    known: bool = Field(description="False: no stamp pair seen yet (offset 0 assumed).")
    offset_ns: Int64 = Field(description="Robot clock - daemon clock now, ns.")
    uncertainty_ns: Int64 | None = Field(
        description="Half-width of the bound around offset_ns, ns; nil: unbounded (only "
                    "one-way robot stamps seen).")
    drift_ppm: float = Field(description="Drift of the robot clock, ppm (1e-6 s/s).")
    age_s: NonNegFloat = Field(description="Seconds since the newest stamp pair (the bound grows "
                                           "while none comes).")
    steps: NonNegInt = Field(description="Step changes of the robot clock detected.")
    warning: Text = Field("", description="Why the offset should not be trusted now (unknown, "
                                          "just jumped, stale); empty: none.")


class DelayStatus(WireModel):
    """Observed delays of one stream on the daemon's timeline (``SessionStatus.delays``)."""

    count: NonNegInt = Field(description="Delays kept (the newest; bounded).")
    p50_ms: float = Field(description="Median delay, ms.")
    p99_ms: float = Field(description="99th percentile delay, ms.")
    max_ms: float = Field(description="Largest delay kept, ms.")


class SessionStatus(Message):
    """Reply of ``pd/p<k>/<session>/status``, and the answer to every config change."""

    session: Name = Field(description="Session id.")
    instance: Name = Field(description="Daemon instance serving the session.")
    state: Literal["active", "restored", "expired", "removed"] = Field(
        description="active; restored (from the state directory after a restart); "
                    "expired (idle too long); removed (config deleted).")
    now_step: Int64 = Field(description="The session's current step.")
    counters: Counters = Field(default_factory=dict, description="Session counters.")
    published: NonNegInt = Field(description="Predictions published so far.")
    latency_p50_us: NonNegFloat = Field(description="Median processing latency, µs.")
    latency_p99_us: NonNegFloat = Field(description="99th percentile processing latency, µs.")
    detail: Text = Field("", description="Free text (e.g. why the session was replaced).")
    origin: Literal["prior", "checkpoint", "replica"] = Field(
        "prior", description="Where the estimate started from: the spec's prior, a checkpoint "
                             "(restart) or a replica (takeover) of step origin_step.")
    origin_step: NonNegInt | None = Field(
        None, description="now_step of the checkpoint or replica resumed from; nil for prior.")
    clock: ClockStatus | None = Field(
        None, description="The robot clock's offset estimate; nil: the session does not map "
                          "robot stamps (its spec's robot_clock is 'shared').")
    delays: dict[Name, DelayStatus] = Field(
        default_factory=dict, description="Learned delays per stream: each sensor by name, "
                                          "'cmd' for issue -> applied (from echoes).")
    recommended_max_delay: NonNegInt | None = Field(
        None, description="Smallest window (steps) that would have refused at most the "
                          "service's late share of the samples as late, + 10 % (<= 1.2x); "
                          "nil: no sample yet.")
    recommended_lead: NonNegInt | None = Field(
        None, description="Median issue -> applied gap of the echoed commands (steps); nil: "
                          "no echo yet.")
    late_share: NonNegFloat = Field(
        0.0, description="Share of the decoded samples refused as late so far.")
    readback: Literal["", "waiting", "answered", "timeout"] = Field(
        "", description="A restarted or taken-over session publishes its first prediction "
                        "only once its senders' caches were read back: waiting (not yet), "
                        "answered (every sensor's and the command's cache answered), timeout "
                        "(2 x recover_timeout_s passed first); empty: the session did not "
                        "wait (started afresh).")
    term: NonNegInt = Field(
        0, description="Ownership term the session is published with (Prediction.term).")


class ServiceStatus(Message):
    """Reply of ``pd/@service/<instance>/status``."""

    instance: Name = Field(description="Daemon instance id.")
    sessions: list[Name] = Field(description="Sessions this instance serves.")
    counters: Counters = Field(default_factory=dict, description="Service-wide counters.")
    latency_p50_us: NonNegFloat = Field(description="Median processing latency, µs.")
    latency_p99_us: NonNegFloat = Field(description="99th percentile processing latency, µs.")
    uptime_s: NonNegFloat = Field(description="Seconds since the instance started.")
    shard: Annotated[str, StringConstraints(max_length=64)] = Field(
        "", description="Which share of the sessions this instance takes, e.g. '0/2'.")
    partitions: Annotated[int, Field(ge=1, le=4096)] = Field(
        1, description="The deployment's partition count P (PD_PARTITIONS) this instance "
        "uses (absent: 1, an instance of key layout 1).")
    key_layout: Annotated[int, Field(ge=1, le=255)] = Field(
        1, description="The key layout this instance speaks, protocol.md section 2 (absent: "
        "1).")
    owned_partitions: NonNegInt = Field(0, description="How many of the P partitions this "
                                        "instance owns now.")
    clock_stepped_ns: int = Field(
        0, description="Sum of the host wall-clock steps (ns, signed) the instance's step clock "
        "followed since it started (counted in ``clock_steps``; 0: none).")


#: Every top-level message type, in protocol order.
MESSAGE_TYPES: tuple[type[Message], ...] = (
    SessionSpec, Measurement, Command, CommandEcho, ClockProbe, ClockProbeReply, Prediction,
    ErrorReport, SessionStatus, ServiceStatus,
)
