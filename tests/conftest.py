"""With ``EVNOISE_TESTS_WITHOUT_READERS=1`` (set by ``.ci/lowest-deps`` only), a test that fails because an
optional camera-file package is not installed (evnoise's own "... needs the faery package ..." error) is reported as
skipped, naming the package: at the dependency floors (NumPy 1.x) faery, tonic and aedat cannot be installed, and
every other test still runs. Without the variable (CI, the README's test command) nothing changes."""

from __future__ import annotations

import importlib.util
import os
import re

import pytest

_NEEDS = re.compile(r"needs the (faery|tonic|aedat) package")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    if os.environ.get("EVNOISE_TESTS_WITHOUT_READERS") != "1":
        return
    report = outcome.get_result()
    if not report.failed or call.excinfo is None:
        return
    found = _NEEDS.search(str(report.longrepr))
    if found and importlib.util.find_spec(found.group(1)) is None:
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0, f"{found.group(1)} is not installed")
