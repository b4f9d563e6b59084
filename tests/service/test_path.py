"""The daemon's PredictedPath (``pd/p<k>/<s>/path``): off by default (nothing else changes),
else one with every ``path.every``-th Prediction, ending at that Prediction's very values,
its points the offline estimator's predict_path."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.wire import SessionSpec, WireError, decode, encode, keys
from pd_service.wire.messages import MAX_PATH_POINTS, PathSpec
from pd_service.wire.path import PredictedPath

from .helpers import paper_spec
from .test_core import PaperFeed, make_core, world  # noqa: F401  (world: a fixture)


def _paths(cli) -> list[tuple[str, bytes]]:
    got: list[tuple[str, bytes]] = []
    cli.subscribe(keys.ALL_PATHS, lambda s: got.append((s.key, bytes(s.payload))))
    return got


@pytest.mark.parametrize("every,stride", [(1, 1), (3, 4)])
def test_paths_end_at_their_predictions_and_match_the_offline_path(request, tmp_path, every,
                                                                   stride):
    bus, clock, col, cli = request.getfixturevalue("world")
    got = _paths(cli)
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, cli, clock, col, "s1", steps=60)
    idx = [0, 1]
    feed.spec = feed.spec.model_copy(update={"path": PathSpec(indices=idx, every=every,
                                                              stride=stride)})
    feed.configure()
    seen = 0
    for k in range(60):
        before = len(got)
        feed.step(k)
        for key, payload in got[before:]:
            assert key == keys.path_key("s1")
            path = decode(payload, PredictedPath)
            pred = next(p for p in col.predictions["s1"] if p.seq == path.seq)
            assert path.seq % every == 0
            assert path.steps[-1] == pred.step and path.newest_step == pred.newest_step
            assert np.array_equal(path.X[-1], pred.x[idx])
            assert np.array_equal(path.covariance(len(path.steps) - 1), pred.P[np.ix_(idx, idx)])
            assert path.t_ns(len(path.steps) - 1) == pred.t_ns
            offline = feed.offline.predict_path(k, stride, MAX_PATH_POINTS)
            assert path.steps == [p.step for p in offline]
            for i, p in enumerate(offline):
                np.testing.assert_allclose(path.X[i], p.x[idx], rtol=1e-9, atol=1e-12)
                np.testing.assert_allclose(path.covariance(i), p.P[np.ix_(idx, idx)],
                                           rtol=1e-9, atol=1e-12)
            seen += 1
    assert seen == len(col.predictions["s1"][::every]) > 10


def test_no_path_unless_the_spec_asks(request, tmp_path):
    bus, clock, col, cli = request.getfixturevalue("world")
    got = _paths(cli)
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, cli, clock, col, "s1", steps=20)
    feed.configure()
    feed.run()
    assert feed.compared > 10 and got == []


def test_path_spec_is_checked():
    spec = paper_spec("s1")
    n = spec.n
    with pytest.raises(WireError, match="path.indices"):
        decode(encode(spec.model_copy(update={"path": PathSpec(indices=[n])})), SessionSpec)
    for bad in ({"indices": []}, {"indices": [0, 0]}, {"indices": list(range(9))},
                {"indices": [0], "every": 0}, {"indices": [0], "stride": 0}):
        with pytest.raises(ValueError):
            PathSpec(**bad)
