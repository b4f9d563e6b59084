"""Restart and takeover without going back to the prior: the checkpoints and replicas of the
sessions' estimator state.

- :mod:`.checkpoint`: EstimatorState <-> SessionState (the wire message), and whether a state
  may be resumed;
- :mod:`.keeper`: :class:`.keeper.HandoverKeeper`, which writes checkpoints, sends and keeps replicas
  and resumes sessions;
- :mod:`.checkpoint_log`: every session's checkpoint in one append-only file;
- :mod:`.checkpoint_writer`: the thread that appends them.
"""
