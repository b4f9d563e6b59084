"""Predictions paired with a simulator's truth by target step: the one pairing of the SDK
(:class:`~pd_client.Display` and the recording / viewing tools use it)."""

from __future__ import annotations

from collections import OrderedDict
from typing import TypeVar

import numpy as np

from pd_service.wire import Prediction

from .truth import Truth

_Kept = TypeVar("_Kept", Prediction, Truth)


def prediction_error(pred: Prediction, truth: Truth) -> np.ndarray | None:
    """``pred.x - truth.x`` (n values), the truth's angle components wrapped into [-pi, pi)
    (an error across +-pi is small, not 2 pi); None when the two states' sizes differ."""
    n = pred.x.shape[0]
    if truth.x.shape[0] != n:
        return None
    err = pred.x - truth.x
    idx = [i for i in truth.angles if i < n]
    if idx:
        err[idx] = (err[idx] + np.pi) % (2.0 * np.pi) - np.pi
    return err


class TruthPairs:
    """The newest ``keep`` predictions and truths of one session, each by its (target) step.

    Adding one returns the other side's entry at its step (its pair), if kept; :attr:`newest`
    is the pair with the newest step so far. Not thread-safe: the caller holds its lock.
    """

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.predictions: OrderedDict[int, Prediction] = OrderedDict()
        self.truths: OrderedDict[int, Truth] = OrderedDict()
        self.newest: tuple[Prediction, Truth] | None = None

    def add_prediction(self, pred: Prediction) -> Truth | None:
        """Keep ``pred`` (replacing one of its step); the truth at its step, or None."""
        _keep(self.predictions, pred.step, pred, self.keep)
        truth = self.truths.get(pred.step)
        if truth is not None:
            self._paired(pred, truth)
        return truth

    def add_truth(self, truth: Truth) -> Prediction | None:
        """Keep ``truth`` (replacing one of its step); the prediction for its step, or None."""
        _keep(self.truths, truth.step, truth, self.keep)
        pred = self.predictions.get(truth.step)
        if pred is not None:
            self._paired(pred, truth)
        return pred

    def _paired(self, pred: Prediction, truth: Truth) -> None:
        if self.newest is None or pred.step >= self.newest[0].step:
            self.newest = (pred, truth)


def _keep(kept: OrderedDict[int, _Kept], step: int, item: _Kept, keep: int) -> None:
    kept[step] = item
    kept.move_to_end(step)
    while len(kept) > keep:
        kept.popitem(last=False)
