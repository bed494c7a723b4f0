"""benchmarks/suite_time.py's pytest plugin: writes each collected test's markers (the project's own, from
pyproject.toml's list) and each test's seconds (setup, call and teardown) to SUITE_TIME_EVENTS, keyed by the node
ids that the probe's events carry (PYTEST_CURRENT_TEST), for the report's tables."""

import collections
import json
import os

_seconds: dict[str, float] = collections.Counter()


def _path(kind: str) -> str:
    return os.path.join(os.environ["SUITE_TIME_EVENTS"], f"{kind}-{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.json")


def pytest_collection_modifyitems(session, config, items):
    if not os.environ.get("SUITE_TIME_EVENTS"):
        return
    ours = {line.split(":", 1)[0].strip() for line in config.getini("markers")} - {"xdist_group"}  # the Ray group
    markers = {item.nodeid.split("@", 1)[0]: sorted({m.name for m in item.iter_markers()} & ours) for item in items}
    with open(_path("markers"), "w") as f:
        json.dump(markers, f)


def pytest_runtest_logreport(report):
    # under pytest-xdist the controller hears each worker's reports again (they carry the worker's node)
    if os.environ.get("SUITE_TIME_EVENTS") and not hasattr(report, "node"):
        _seconds[report.nodeid.split("@", 1)[0]] += report.duration


def pytest_sessionfinish(session):
    if os.environ.get("SUITE_TIME_EVENTS") and _seconds:
        with open(_path("durations"), "w") as f:
            json.dump(_seconds, f)
