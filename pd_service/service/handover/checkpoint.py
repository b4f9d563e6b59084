"""EstimatorState <-> SessionState (the wire message), and whether a state may be resumed.

A state is resumed only if it is the same version, was taken from an estimator built from
the very same spec (fingerprint of the encoded spec), is not from the future and restores
cleanly; otherwise :func:`refusal` names the reason and the session starts from its prior:

============  =======================================================================
version       ``state_version`` is not this build's
spec          ``spec_fingerprint`` differs (the spec changed) or another session
future        taken at a step after the current one (+1): another clock, or a bad one
corrupt       undecodable, or the estimator's restore_state refused it (reason given)
============  =======================================================================

A state older than the window (``now_step - state.now_step > max_delay``: a restart or a
takeover that took longer than the window) is resumed all the same (:func:`is_stale`): the
estimator commits its window at the next step and propagates the committed estimate forward
with the commands it knows (the held command past them), its covariance growing by Q per
step, which is far nearer the truth than the prior.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from pydantic import ValidationError

from pd_service.estimation import STATE_VERSION, Estimator, EstimatorState, StateError
from pd_service.wire import MAX_MESSAGE_BYTES, SessionSpec, WireError, decode, encode
from pd_service.wire.codec import error_kind, validation_reason
from pd_service.wire.session_state import (
    PACK_WITH_ARRAYS,
    SessionState,
    StateCommand,
    StatePacket,
    Tensors,
    pack_state_fields,
)

__all__ = ["Refused", "encode_state", "from_message", "is_stale", "refusal", "restore",
           "to_message"]


@dataclass(frozen=True, slots=True)
class Refused:
    """Why a state was not resumed: ``reason`` one of version / spec / future / corrupt."""

    reason: str
    text: str


def to_message(st: EstimatorState, *, session: str, instance: str, fingerprint: str,
               made_ns: int, session_counters: dict[str, int] | None = None,
               published: int = 0, seq: int = 0, term: int = 0) -> SessionState:
    """The wire form of ``st`` (see :class:`~pd_service.wire.session_state.SessionState`)."""
    base = dict(st.base)
    x, P = st.mean, st.cov
    if "mu" not in base:  # linear / UKF: x and P are the base itself, sent once
        base.pop("x"), base.pop("P")
    return SessionState(
        session=session, instance=instance, spec_fingerprint=fingerprint,
        state_version=st.version, kind=st.kind, made_ns=made_ns, now_step=st.now,
        committed_step=st.committed_step, base_step=st.base_step,
        newest_committed=st.newest_committed, x=x, P=0.5 * (P + P.T), base=base,
        packets=[StatePacket(step=s, sensor=name, z=z, R=R, offset=off)
                 for s, name, z, R, off in st.packets],
        u_origin=st.u_origin,
        commands=[StateCommand(step=j, u=u, offset=st.command_offsets.get(j, 0.0))
                  for j, u in st.commands],
        u_before=st.u_before,
        counters=dict(st.counters), extras=dict(st.extras),
        session_counters=dict(session_counters or {}), published=published, seq=seq,
        term=term)


#: The checkpoints' msgpack in C (pd_service/wire/_encode.c ``pack``), None where the hot
#: path runs as pure Python: :func:`encode_state`'s Python form is the reference.
_PACK: Final = PACK_WITH_ARRAYS


def _as_array(a: Any) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def _as_arrays(arrays: list[Any]) -> list[np.ndarray]:
    return [np.asarray(a, dtype=np.float64) for a in arrays]


def _fields(st: EstimatorState, tensor: Callable[[Any], Any],
            rows: Callable[[list[Any]], list[Any]], *, session: str, instance: str,
            fingerprint: str, made_ns: int, session_counters: dict[str, int] | None,
            published: int, seq: int, term: int) -> dict[str, Any]:
    """A SessionState's fields in wire order (the ``model_dump()`` form), each array given
    by ``tensor`` (and a list of arrays of one shape by ``rows``): its wire form
    (:class:`Tensors`) for msgpack, or the array itself for the C form."""
    base = dict(st.base)
    x, P = st.mean, st.cov
    if "mu" not in base:
        base.pop("x"), base.pop("P")
    P = np.asarray(P, dtype=np.float64)
    return {
        "v": 1, "session": session, "instance": instance, "spec_fingerprint": fingerprint,
        "state_version": int(st.version), "kind": st.kind, "made_ns": int(made_ns),
        "now_step": None if st.now is None else int(st.now),
        "committed_step": int(st.committed_step), "base_step": int(st.base_step),
        "newest_committed": None if st.newest_committed is None else int(st.newest_committed),
        "x": tensor(x),
        "P": tensor(0.5 * (P + P.T)),
        "base": {k: tensor(v) for k, v in base.items()},
        "packets": [{"step": int(s), "sensor": name, "z": tensor(z),
                     "R": None if R is None else tensor(R), "offset": float(off)}
                    for s, name, z, R, off in st.packets],
        "u_origin": tensor(st.u_origin),
        "commands": [{"step": int(j), "u": u, "offset": float(st.command_offsets.get(j, 0.0))}
                     for (j, _), u in
                     zip(st.commands, rows([u for _, u in st.commands]), strict=True)],
        "u_before": None if st.u_before is None else tensor(st.u_before),
        "counters": {str(k): int(v) for k, v in st.counters.items()},
        "extras": {k: tensor(v) for k, v in st.extras.items()},
        "session_counters": {str(k): int(v) for k, v in (session_counters or {}).items()},
        "published": int(published), "seq": int(seq), "term": int(term),
    }


def encode_state(st: EstimatorState, *, session: str, instance: str, fingerprint: str,
                 made_ns: int, session_counters: dict[str, int] | None = None,
                 published: int = 0, seq: int = 0, term: int = 0) -> bytes:
    """``encode(to_message(...))``, byte for byte, without building the models when the
    state is ordinary (finite, small enough). Where the C kernel is built, the fields go
    to it with their arrays as they are (``_encode.pack``: no dicts and lists of floats
    for the arrays' wire form, no msgpack walk over them); else, or if it declines, they
    are built in their wire form and packed by msgpack (cheaper than the models).
    Anything unusual takes the validated path: WireError if it is refused."""
    def fields(tensor: Callable[[Any], Any],
               rows: Callable[[list[Any]], list[Any]]) -> dict[str, Any]:
        return _fields(st, tensor, rows, session=session, instance=instance,
                       fingerprint=fingerprint, made_ns=made_ns,
                       session_counters=session_counters, published=published, seq=seq,
                       term=term)

    data: bytes | None = None
    if _PACK is not None:
        data = _PACK(fields(_as_array, _as_arrays))
        if data is not None and len(data) > MAX_MESSAGE_BYTES:
            data = None
    if data is None:
        t = Tensors()  # the wire form of each array; whether all were finite
        data = pack_state_fields(fields(t, t.rows), t.finite)
    if data is None:
        try:
            msg = to_message(st, session=session, instance=instance, fingerprint=fingerprint,
                             made_ns=made_ns, session_counters=session_counters,
                             published=published, seq=seq, term=term)
        except ValidationError as exc:
            raise WireError(validation_reason("SessionState", exc), error_kind(exc)) from None
        data = encode(msg)
    return data


def from_message(msg: SessionState, n: int) -> EstimatorState:
    """The EstimatorState ``msg`` describes (arrays copied, writable)."""
    base = {k: np.array(v) for k, v in msg.base.items()}
    if "mu" not in base:
        base["x"], base["P"] = np.array(msg.x), np.array(msg.P)
    return EstimatorState(
        kind=msg.kind, n=n, now=msg.now_step, committed_step=msg.committed_step,
        base_step=msg.base_step, newest_committed=msg.newest_committed, base=base,
        packets=[(p.step, p.sensor, np.array(p.z), None if p.R is None else np.array(p.R),
                  p.offset) for p in msg.packets],
        inputs_origin=msg.base_step, u_origin=np.array(msg.u_origin).reshape(-1),
        commands=[(c.step, np.array(c.u).reshape(-1)) for c in msg.commands],
        command_offsets={c.step: c.offset for c in msg.commands if c.offset > 0.0},
        u_before=None if msg.u_before is None else np.array(msg.u_before).reshape(-1),
        counters=dict(msg.counters), extras={k: np.array(v) for k, v in msg.extras.items()},
        version=msg.state_version)


def refusal(msg: SessionState, spec: SessionSpec, fingerprint: str,
            now_step: int) -> Refused | None:
    """Why ``msg`` must not be resumed for ``spec`` at ``now_step`` (None: it may be)."""
    if msg.state_version != STATE_VERSION:
        return Refused("version", f"state version {msg.state_version}, this build reads "
                       f"{STATE_VERSION}")
    if msg.session != spec.session or msg.spec_fingerprint != fingerprint:
        return Refused("spec", "taken from another spec (fingerprint "
                       f"{msg.spec_fingerprint[:12]}, the spec's is {fingerprint[:12]})")
    taken = msg.now_step if msg.now_step is not None else 0
    if taken > now_step + 1:
        return Refused("future", f"taken at step {taken}, after the current step {now_step}")
    return None


def is_stale(msg: SessionState, spec: SessionSpec, now_step: int) -> bool:
    """``msg`` was taken more than the window (``max_delay`` steps) before ``now_step``:
    resumed, it is propagated forward (module docstring)."""
    taken = msg.now_step if msg.now_step is not None else 0
    return now_step - taken > spec.max_delay


def restore(est: Estimator, data: bytes | SessionState, spec: SessionSpec, fingerprint: str,
            now_step: int) -> tuple[SessionState | None, Refused | None]:
    """Decode, check and restore ``data`` into ``est`` (built from ``spec``). Returns the
    message and None when ``est`` now continues from it, else (message or None, Refused);
    ``est`` is unchanged on refusal."""
    if isinstance(data, SessionState):
        msg = data
    else:
        try:
            msg = decode(data, SessionState)
        except WireError as exc:
            return None, Refused("corrupt", exc.reason)
    why = refusal(msg, spec, fingerprint, now_step)
    if why is not None:
        return msg, why
    restore_state = getattr(est, "restore_state", None)
    if restore_state is None:
        return msg, Refused("corrupt", f"{type(est).__name__} cannot restore a state")
    try:
        restore_state(from_message(msg, est.n))
    except StateError as exc:
        return msg, Refused("corrupt", str(exc))
    return msg, None

