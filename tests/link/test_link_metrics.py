"""pd-link's metrics (``pd-link --metrics``): relay counters and per-rule counters labelled by
direction and rule, read back with prometheus-client's own parser."""

from __future__ import annotations

import logging

from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families
from test_link_memory import Link

from pd_service.link.relay import link_metrics
from pd_service.metrics import registry_of
from pd_service.wire import keys


def test_rule_counters_are_labelled_by_direction_and_rule() -> None:
    link = Link({"downlink": [{"name": "cam", "match": "robot/*/*/sensor/camera", "delay": 10}],
                 "uplink": [{"name": "cmd", "delay": 5}]})
    for i in range(3):
        link.client.put(keys.robot_sensor_key("m", "camera"), b"c%d" % i)
    link.client.put(keys.command_key("m"), b"u")
    link.at(100)
    text = generate_latest(registry_of(lambda: link_metrics(link.relay),
                                       logging.getLogger("test"))).decode()
    fams = {f.name: f for f in text_string_to_metric_families(text)}
    forwarded = {(s.labels["direction"], s.labels["rule"]): s.value
                 for s in fams["pd_link_rule_forwarded"].samples if s.name.endswith("_total")}
    assert forwarded[("downlink", "cam")] == 3 and forwarded[("uplink", "cmd")] == 1
    assert fams["pd_link_pending"].samples[0].value == 0
    for fam in fams.values():
        assert fam.name.startswith("pd_link_")
        for s in fam.samples:
            assert set(s.labels) <= {"direction", "rule"}
            if fam.type == "counter":
                assert s.name.endswith(("_total", "_created"))
