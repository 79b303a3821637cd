"""The test tiers of tests/conftest.py: every path it names exists, and every collected test
has exactly one tier."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import INTEGRATION_PATHS, SLOW, TIERS

ROOT = Path(__file__).resolve().parents[1]


def test_every_integration_path_names_a_file_or_folder():
    for prefix in INTEGRATION_PATHS:
        folder, _, start = prefix.rpartition("/")
        matches = [path for path in (ROOT / folder).glob(f"{start}*") if path.exists()]
        assert matches, f"tests/conftest.py INTEGRATION_PATHS names {prefix!r}: no such file"


def test_every_slow_entry_names_a_test_file():
    for node in SLOW:
        assert (ROOT / node.split("::")[0]).is_file(), f"tests/conftest.py SLOW names {node!r}"


def test_every_collected_test_has_one_tier(request):
    for item in request.session.items:
        tiers = [name for name in TIERS if item.get_closest_marker(name)]
        assert len(tiers) == 1, f"{item.nodeid} has the tiers {tiers}"
