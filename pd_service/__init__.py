"""pd-service: networked predictive display for teleoperation.

Layers (imports point one way): ``estimation`` (pure numpy) <- ``wire`` (schemas, codec,
keys) <- ``service`` / ``link`` (Zenoh adapters).
"""

__version__ = "0.1.0"
