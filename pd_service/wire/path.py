"""The predicted path (``pd/p<k>/<session>/path``): the states from the newest measured step to
the predicted step, published beside a Prediction when the session's spec asks for it
(:class:`~.messages.PathSpec`). Encoded with the protocol's msgpack codec
(:func:`pd_service.wire.encode` / ``decode``); docs/protocol.md section 3 and
``docs/schemas/PredictedPath.json``.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from .arrays import Matrix, psd_problem
from .base import invalid
from .messages import MAX_DIM, MAX_PATH_COMPONENTS, MAX_PATH_POINTS, Int64, Message, Name, NonNegInt

PathSteps = Annotated[list[NonNegInt], Field(min_length=1, max_length=MAX_PATH_POINTS)]


class PredictedPath(Message):
    """Predicted means and covariances of components ``indices`` at steps ``steps``.

    Rules: ``steps`` strictly increasing, the last is the Prediction's target step (the
    Prediction with the same ``seq``); X is k x d (k = len(steps), d = len(indices)); P is
    k x d*d, row i the row-major d x d covariance at steps[i], each symmetric PSD.
    """

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="seq of the Prediction this path ends at.")
    steps: PathSteps = Field(description="Steps of the points, increasing: the newest measured "
                                         "step (or the committed base) first, the target last.")
    period_ns: Annotated[int, Field(ge=1, le=2**63 - 1)] = Field(
        description="Step period, ns: point i is at t0_ns + (steps[i] - steps[0]) * period_ns.")
    t0_ns: Int64 = Field(description="Start time of steps[0], ns.")
    indices: Annotated[list[Annotated[int, Field(ge=0, le=MAX_DIM - 1)]],
                       Field(min_length=1, max_length=MAX_PATH_COMPONENTS)] = Field(
        description="State components carried (the spec's path.indices).")
    X: Matrix = Field(description="Means, k x d.")
    P: Matrix = Field(description="Covariances, k x d*d (row-major d x d blocks).")
    newest_step: NonNegInt | None = Field(
        None, description="Newest sample step among the measurements used; nil before any.")
    made_ns: Int64 = Field(description="When it was computed, ns on the shared clock.")

    @model_validator(mode="after")
    def _check(self) -> PredictedPath:
        k, d = len(self.steps), len(self.indices)
        if any(b <= a for a, b in pairwise(self.steps)):
            raise invalid("steps", "must be strictly increasing")
        if self.X.shape != (k, d):
            raise invalid("X", f"must be {k}x{d}, got shape {list(self.X.shape)}")
        if self.P.shape != (k, d * d):
            raise invalid("P", f"must be {k}x{d * d}, got shape {list(self.P.shape)}")
        for i in range(k):
            problem = psd_problem(self.P[i].reshape(d, d))
            if problem:
                raise invalid("P", f"point {i}: {problem}")
        return self

    def covariance(self, i: int) -> np.ndarray:
        """The d x d covariance of point ``i``."""
        d = len(self.indices)
        return np.asarray(self.P[i]).reshape(d, d)

    def t_ns(self, i: int) -> int:
        """Start time of point ``i``'s step, ns."""
        return self.t0_ns + (self.steps[i] - self.steps[0]) * self.period_ns
