"""Derived files (window caches, action statistics) never land inside the installed packages."""

from __future__ import annotations

from policies.learned.batches import load_splits
from policies.learned.data import STATS_FILENAME, load_or_compute_stats
from policies.learned.data_cache import CACHE_ENV, derived_dir
from riskflow_env.scenarios.io import ASSETS


def _listing(folder) -> set[str]:
    return {str(path.relative_to(folder)) for path in folder.rglob("*")}


def test_shipped_bank_splits_and_stats_write_nothing_into_the_package(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    shipped = ASSETS / "train"
    before = _listing(ASSETS)
    train, _ = load_splits(shipped, None, 0.2, stride=80)
    load_or_compute_stats(shipped, train)
    assert _listing(ASSETS) == before
    cached = derived_dir(shipped)
    assert cached.is_relative_to(tmp_path / "user-cache")
    assert (cached / STATS_FILENAME).is_file() and any((cached / "cache").iterdir())


def test_user_folders_keep_their_files_beside_the_data(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    data = tmp_path / "data"
    data.mkdir()
    assert derived_dir(data) == data.resolve()


def test_read_only_folders_use_the_user_cache(monkeypatch, tmp_path):
    """Also for root, whom the permission check lets write anywhere: a folder without write
    bits is left as it is."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    data = tmp_path / "data"
    data.mkdir()
    data.chmod(0o555)
    try:
        assert derived_dir(data).is_relative_to(tmp_path / "user-cache")
    finally:
        data.chmod(0o755)


def test_the_user_cache_key_follows_the_folder_contents(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "user-cache"))
    monkeypatch.setattr("policies.learned.data_cache.PACKAGE_DIRS", (tmp_path,))
    data = tmp_path / "data"
    data.mkdir()
    (data / "a.npz").write_bytes(b"one")
    first = derived_dir(data)
    assert first.is_relative_to(tmp_path / "user-cache") and derived_dir(data) == first
    (data / "a.npz").write_bytes(b"three")  # new scenes: new statistics, not stale ones
    assert derived_dir(data) != first
