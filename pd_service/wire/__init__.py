"""Wire protocol of pd-service: message schemas, msgpack codec, key expressions.

Imports numpy, pydantic and msgpack, never zenoh. What a message means for its session
(steps, checks, Prediction encoding) lives in :mod:`pd_service.wire.convert` (not imported
here); a SessionSpec becomes an estimator in :mod:`pd_service.backends`.

```python
from pd_service.wire import encode, decode, WireError, Measurement
data = encode(msg)                 # bytes, <= 64 KiB
msg = decode(data, Measurement)    # raises WireError, and nothing else, for any bad input
```
"""

from . import keys
from .arrays import MAX_DIM, PSD_RTOL, Matrix, Vector, psd_problem
from .codec import MAX_MESSAGE_BYTES, decode, encode
from .errors import WireError
from .messages import (
    CONFIG_RATE_LIMITED,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    ClockProbe,
    ClockProbeReply,
    ClockStatus,
    Command,
    CommandEcho,
    DelayStatus,
    ErrorReport,
    ImmModelSpec,
    LinearModelSpec,
    Measurement,
    Message,
    ModelSpec,
    Prediction,
    SensorSpec,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    UnscentedModelSpec,
)
from .session_state import SessionState, spec_fingerprint

__all__ = [
    "CONFIG_RATE_LIMITED",
    "MAX_DIM",
    "MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "PSD_RTOL",
    "SCHEMA_VERSION",
    "ClockProbe",
    "ClockProbeReply",
    "ClockStatus",
    "Command",
    "CommandEcho",
    "DelayStatus",
    "ErrorReport",
    "ImmModelSpec",
    "LinearModelSpec",
    "Matrix",
    "Measurement",
    "Message",
    "ModelSpec",
    "Prediction",
    "SensorSpec",
    "ServiceStatus",
    "SessionSpec",
    "SessionState",
    "SessionStatus",
    "UnscentedModelSpec",
    "Vector",
    "WireError",
    "decode",
    "encode",
    "keys",
    "psd_problem",
    "spec_fingerprint",
]
