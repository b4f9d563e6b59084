"""pd_client: Python SDK for pd-service (robot, operator, display and admin sides).

```python
import pd_client

transport = pd_client.connect("tcp/127.0.0.1:7447")           # Zenoh, client mode
with pd_client.Robot(transport, "s1") as robot:
    robot.publish("camera", [1.0, 5.0], step=k)                 # measurement of step k
with pd_client.Operator(transport, "s1") as op:
    op.send([0.5], step=k + lead)                               # command applying at k + lead
with pd_client.Display(transport, "s1") as display:
    pred = display.wait(timeout=5.0)                            # Prediction of x(k + lead)
with pd_client.Admin(transport) as admin:
    admin.wait_for_service(timeout=10.0)
    admin.open_session(spec)                                    # SessionSpec
```
For unit tests, pass a ``pd_service.transport.InMemoryBus().transport()`` instead.
"""

from pd_service.transport import InMemoryBus
from pd_service.wire import Command, Measurement, Prediction, SessionSpec, SessionStatus

from ._base import connect
from .admin import Admin
from .display import Display, DisplayStats
from .errors import (
    AccessDenied,
    InvalidMessage,
    PdClientError,
    ServiceUnavailable,
    SessionExists,
    SessionNotFound,
    SessionRefused,
    Timeout,
)
from .operator import Operator
from .robot import CommandSchedule, Robot
from .truth import Truth

__all__ = [
    "AccessDenied",
    "Admin",
    "Command",
    "CommandSchedule",
    "Display",
    "DisplayStats",
    "InMemoryBus",
    "InvalidMessage",
    "Measurement",
    "Operator",
    "PdClientError",
    "Prediction",
    "Robot",
    "ServiceUnavailable",
    "SessionExists",
    "SessionNotFound",
    "SessionRefused",
    "SessionSpec",
    "SessionStatus",
    "Timeout",
    "Truth",
    "connect",
]
