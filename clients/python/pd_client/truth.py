"""Ground truth of a simulated robot (``robot/p<k>/<session>/truth``): the wire's
:class:`pd_service.wire.truth.Truth`, here for the clients that publish and read it."""

from pd_service.wire.truth import StateName, Truth

__all__ = ["StateName", "Truth"]
