"""The one gate in front of the tests on real captures and logs (``conftest.shared_path``): a missing
``../shared`` skips them on a developer's machine and fails them in CI, where a skip would pass."""

import sys

import pytest


def test_missing_shared_data_skips_locally_and_fails_in_ci(shared_file, monkeypatch, tmp_path):
    conftest = sys.modules[shared_file.__module__]
    monkeypatch.setattr(conftest, "SHARED", tmp_path / "no-shared")
    for value in (None, "false", ""):
        if value is None:
            monkeypatch.delenv("CI", raising=False)
        else:
            monkeypatch.setenv("CI", value)
        with pytest.raises(pytest.skip.Exception, match="shared data not found"):
            shared_file("data", "logs", "x.bag")
    for value in ("true", "TRUE", "1"):
        monkeypatch.setenv("CI", value)
        with pytest.raises(pytest.fail.Exception, match="CI=true"):
            shared_file("data", "logs", "x.bag")
    (tmp_path / "no-shared" / "data").mkdir(parents=True)
    assert shared_file("data") == tmp_path / "no-shared" / "data"  # present: no skip, no failure, even in CI
