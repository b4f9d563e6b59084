"""pd_client: Python SDK for pd-service (robot, operator, display, admin sides)."""

__all__: list[str] = []
