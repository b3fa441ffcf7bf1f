"""``python -m tmrl --install --env tm20lidar``: the original's resources archive, served over a
loopback HTTP server, set up in a temporary home folder holding ``OpenplanetNext`` and a temporary
data folder (tests/conftest.py gives each test both); hostile archives refused whole; offline."""

from __future__ import annotations

import json
import os
import pickle
import stat
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from tm_resources_support import REWARD, ArchiveServer, archive, declare_size, members, plugin_bytes

from tmrl import cli
from tmrl.tm.resources import URL_ENV

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def home(tmp_path):
    """The conftest's home folder, with the OpenplanetNext folder the game makes."""
    h = Path(os.environ["HOME"])
    (h / "OpenplanetNext").mkdir(parents=True)
    return h


def install(monkeypatch, capsys, url, env="tm20lidar"):
    monkeypatch.setenv(URL_ENV, url)
    rc = cli.main(["--install", "--env", env])
    out = capsys.readouterr()
    return rc, out.out, out.err


def err_lines(err: str) -> list[str]:
    """stderr without the download's progress line (stderr is not a terminal here: one line at the end)."""
    return [line for line in err.strip().splitlines() if not line.endswith(" downloaded")]


def everything_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")} if folder.exists() else set()


# ------------------------------------------------------------------------ the whole setup
def test_install_sets_up_the_game_side_and_keeps_config_edits(tmp_path, home, _isolated_data_folder):
    """The quality bar, as a user runs it: a config.json edited beforehand, then the command in a
    process of its own against the served archive."""
    data = _isolated_data_folder
    env = dict(os.environ, PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-m", "tmrl", "--install"], env=env, check=True, capture_output=True, timeout=120)
    cfg_file = data / "config" / "config.json"
    cfg = json.loads(cfg_file.read_text())
    cfg["PASSWORD"], cfg["BATCH_SIZE"] = "our-own-secret", 128
    cfg_file.write_text(json.dumps(cfg))
    body = archive()
    with ArchiveServer(body) as server:
        proc = subprocess.run([sys.executable, "-m", "tmrl", "--install", "--env", "tm20lidar"], check=False,
                              env=dict(env, **{URL_ENV: server.url}), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert server.requests == 1
    assert server.url in proc.stdout  # says what it fetches and from where
    plugins = home / "OpenplanetNext" / "Plugins"
    for name in ("TMRL_GrabData.op", "TMRL_SaveGhost.op"):
        assert (plugins / name).read_bytes() == members()[f"resources/Plugins/{name}"]
    assert "TMRL_GrabData.op v0.3 installed" in proc.stdout
    from tmrl.tm.record import load_reward

    np.testing.assert_array_equal(load_reward(data / "reward" / "reward.npy"), REWARD)
    np.testing.assert_array_equal(load_reward(data / "reward" / "tmrl-test.npy"), REWARD)
    from safetensors.torch import load_file

    lidar = load_file(str(data / "weights" / "SAC_4_LIDAR_pretrained.tmod"))
    imgs = load_file(str(data / "weights" / "SAC_4_imgs_pretrained.tmod"))
    assert "net.0.weight" in lidar and any(k.startswith("encoder.convs.") for k in imgs)
    assert "--worker --test` drives with it" in proc.stdout
    after = json.loads(cfg_file.read_text())
    assert after["PASSWORD"] == "our-own-secret" and after["BATCH_SIZE"] == 128  # the user's edits
    assert after["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR" and after["RUN_NAME"] == "SAC_4_LIDAR_pretrained"
    assert "docs/" not in proc.stdout  # messages give a --help topic, never a repository path


def test_a_second_run_changes_nothing_and_fetches_nothing(monkeypatch, capsys, home, _isolated_data_folder):
    with ArchiveServer(archive()) as server:
        assert install(monkeypatch, capsys, server.url)[0] == 0
        weights = _isolated_data_folder / "weights" / "SAC_4_LIDAR_pretrained.tmod"
        before = weights.stat().st_mtime_ns
        rc, out, _ = install(monkeypatch, capsys, server.url)
        assert rc == 0 and server.requests == 1  # the archive kept in resources/ is used again
    assert "already there, unchanged" in out and "already imported" in out
    assert weights.stat().st_mtime_ns == before


def test_a_different_plugin_is_replaced_and_the_summary_says_so(monkeypatch, capsys, home):
    plugins = home / "OpenplanetNext" / "Plugins"
    plugins.mkdir()
    (plugins / "TMRL_GrabData.op").write_bytes(plugin_bytes("TMRL Grab Data", "0.1"))
    with ArchiveServer(archive()) as server:
        rc, out, _ = install(monkeypatch, capsys, server.url)
    assert rc == 0
    assert "TMRL_GrabData.op v0.3 replaced a different copy (v0.1)" in out
    assert (plugins / "TMRL_GrabData.op").read_bytes() == members()["resources/Plugins/TMRL_GrabData.op"]


def test_weights_trained_since_and_another_maps_reward_are_kept(monkeypatch, capsys, home, _isolated_data_folder):
    data = _isolated_data_folder
    mine = np.c_[np.zeros(50), np.arange(50.0), np.zeros(50)]
    from tmrl.tm.record import load_reward, save_reward

    save_reward(mine, data / "reward" / "reward.npy")
    (data / "weights").mkdir(parents=True)
    (data / "weights" / "SAC_4_LIDAR_pretrained.tmod").write_bytes(b"trained since")
    with ArchiveServer(archive()) as server:
        rc, out, _ = install(monkeypatch, capsys, server.url)
    assert rc == 0
    np.testing.assert_array_equal(load_reward(data / "reward" / "reward.npy"), mine)
    assert (data / "weights" / "SAC_4_LIDAR_pretrained.tmod").read_bytes() == b"trained since"
    assert "kept your" in out and "tmrl-test.npy" in out


def test_without_openplanet_it_says_where_it_looked_and_still_sets_up_the_rest(monkeypatch, capsys,
                                                                               _isolated_data_folder):
    with ArchiveServer(archive()) as server:
        rc, out, _ = install(monkeypatch, capsys, server.url)
    assert rc == 0
    line = next(x for x in out.splitlines() if x.strip().startswith("plugins"))
    assert "not copied" in line and "OpenplanetNext" in line and "OPENPLANET_FOLDER" in line
    assert (_isolated_data_folder / "weights" / "SAC_4_LIDAR_pretrained.tmod").is_file()


def test_the_openplanet_folder_setting_overrides_the_search(monkeypatch, capsys, tmp_path, home):
    elsewhere = tmp_path / "games" / "OpenplanetNext"
    elsewhere.mkdir(parents=True)
    with ArchiveServer(archive()) as server:
        monkeypatch.setenv(URL_ENV, server.url)
        rc = cli.main(["--install", "--env", "tm20lidar", "-d", json.dumps({"OPENPLANET_FOLDER": str(elsewhere)})])
    assert rc == 0
    assert (elsewhere / "Plugins" / "TMRL_GrabData.op").is_file()
    assert not (home / "OpenplanetNext" / "Plugins").exists()


def test_proton_prefix_is_searched_after_the_home_folder(tmp_path):
    from tmrl.tm.plugins import find_openplanet

    h = tmp_path / "h"
    prefix = h / ".local/share/Steam/steamapps/compatdata/2225070/pfx/drive_c/users/steamuser/OpenplanetNext"
    prefix.mkdir(parents=True)
    assert find_openplanet(home=h, environ={}, system="Linux").folder == prefix
    (h / "OpenplanetNext").mkdir()
    assert find_openplanet(home=h, environ={}, system="Linux").folder == h / "OpenplanetNext"
    win = tmp_path / "profile"
    (win / "OpenplanetNext").mkdir(parents=True)
    found = find_openplanet(home=h, environ={"USERPROFILE": str(win)}, system="Windows")
    assert found.folder == win / "OpenplanetNext"


# ------------------------------------------------------------------------ offline, then online
def test_offline_says_what_to_download_and_a_second_run_finishes(monkeypatch, capsys, home, port_factory,
                                                                _isolated_data_folder):
    data = _isolated_data_folder
    refused = f"http://127.0.0.1:{port_factory()}/resources.zip"  # nothing listens there
    rc, out, err = install(monkeypatch, capsys, refused)
    assert rc == 0, err
    offline = [line for line in out.splitlines() if line.strip().startswith("offline:")]
    assert len(offline) == 1
    assert refused in offline[0] and str(data / "resources" / "resources.zip") in offline[0]
    assert (data / "config" / "config.json").is_file() and (data / "credentials").is_dir()  # the rest exists
    assert not (home / "OpenplanetNext" / "Plugins").exists()
    with ArchiveServer(archive()) as server:
        rc, out, _ = install(monkeypatch, capsys, server.url)
    assert rc == 0 and (home / "OpenplanetNext" / "Plugins" / "TMRL_GrabData.op").is_file()
    assert (data / "weights" / "SAC_4_LIDAR_pretrained.tmod").is_file()


def test_an_archive_downloaded_by_hand_is_used_from_the_data_folder(monkeypatch, capsys, home, port_factory,
                                                                   _isolated_data_folder, tmp_path):
    hand = _isolated_data_folder / "resources" / "resources.zip"
    hand.parent.mkdir(parents=True)
    hand.write_bytes(archive())
    rc, out, _ = install(monkeypatch, capsys, f"http://127.0.0.1:{port_factory()}/x.zip")
    assert rc == 0 and "offline:" not in out
    assert (home / "OpenplanetNext" / "Plugins" / "TMRL_SaveGhost.op").is_file()


def test_file_addresses_work(monkeypatch, capsys, home, tmp_path):
    src = tmp_path / "mirror" / "resources.zip"
    src.parent.mkdir()
    src.write_bytes(archive())
    rc, _, _ = install(monkeypatch, capsys, src.as_uri())
    assert rc == 0 and (home / "OpenplanetNext" / "Plugins" / "TMRL_GrabData.op").is_file()


# ------------------------------------------------------------------------ hostile archives
def _symlink() -> tuple[zipfile.ZipInfo, bytes]:
    info = zipfile.ZipInfo("resources/Plugins/link.op")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info, b"../../../../.bashrc"


class Evil:
    """A pickle that, unpickled by pickle.load, would create the file ``marker``."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('ran')",))


def hostile(kind: str, tmp_path: Path) -> tuple[bytes, str]:
    """A hostile archive of ``kind`` and the member its refusal must name."""
    full = members()
    if kind == "dotdot":
        return archive(full, [("../../evil.txt", b"evil")]), "../../evil.txt"
    if kind == "absolute":
        return archive(full, [(str(tmp_path / "evil-abs.txt"), b"evil")]), str(tmp_path / "evil-abs.txt")
    if kind == "symlink":
        return archive(full, [_symlink()]), "resources/Plugins/link.op"
    if kind == "huge":
        return declare_size(archive(full), "resources/SAC_4_LIDAR_pretrained.tmod", 2 * 2**30), \
            "resources/SAC_4_LIDAR_pretrained.tmod"
    if kind == "pickle":
        full["resources/reward.pkl"] = pickle.dumps(Evil(str(tmp_path / "pwned")))
        return archive(full), "resources/reward.pkl"
    if kind == "layout":
        del full["resources/reward.pkl"]
        return archive(full), "resources/reward.pkl"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind, rule", [
    ("dotdot", "'..'"), ("absolute", "absolute path"), ("symlink", "symbolic link"),
    ("huge", "2147483648 bytes, over the"), ("pickle", "not a NumPy array of numbers"), ("layout", "is missing"),
])
def test_hostile_archives_are_refused_whole_in_one_line(monkeypatch, capsys, tmp_path, home, kind, rule,
                                                        _isolated_data_folder):
    body, member = hostile(kind, tmp_path)
    outside = lambda: everything_under(tmp_path) - everything_under(_isolated_data_folder) - {_isolated_data_folder}
    before = outside()
    with ArchiveServer(body) as server:
        rc, _, err = install(monkeypatch, capsys, server.url)
    assert rc == 2
    lines = err_lines(err)
    assert len(lines) == 1 and lines[0].startswith("tmrl: error: refused the resources archive"), err
    assert repr(member) in lines[0] and rule in lines[0], lines[0]
    # nothing written outside the data folder: no plugin copied, no evil file, no pickle run
    after = outside()
    assert after == before, after - before
    assert not (home / "OpenplanetNext" / "Plugins").exists()
    assert not (_isolated_data_folder / "resources" / "resources.zip").exists()  # a refused download is not kept
    assert not (tmp_path / "pwned").exists() and not list(tmp_path.rglob("evil*"))


def test_sha256_mismatch_is_refused_when_a_digest_is_configured(monkeypatch, capsys, home):
    body = archive()
    import hashlib

    with ArchiveServer(body) as server:
        monkeypatch.setenv("TMRL_RESOURCES_SHA256", "0" * 64)
        rc, _, err = install(monkeypatch, capsys, server.url)
        assert rc == 2 and "SHA-256 is" in err and "(the archive)" in err
        monkeypatch.setenv("TMRL_RESOURCES_SHA256", hashlib.sha256(body).hexdigest())
        rc, _, err = install(monkeypatch, capsys, server.url)
        assert rc == 0, err


def test_a_tmod_that_holds_code_is_refused_and_runs_nothing(monkeypatch, capsys, home, tmp_path):
    full = members()
    full["resources/SAC_4_LIDAR_pretrained.tmod"] = pickle.dumps(Evil(str(tmp_path / "pwned")))
    with ArchiveServer(archive(full)) as server:
        rc, _, err = install(monkeypatch, capsys, server.url)
    assert rc == 2 and "'resources/SAC_4_LIDAR_pretrained.tmod'" in err and len(err_lines(err)) == 1
    assert not (tmp_path / "pwned").exists()
    assert not (home / "OpenplanetNext" / "Plugins").exists()


def test_the_restricted_reader_reads_what_the_original_recorder_wrote():
    from tmrl.tm.record import read_legacy_reward_bytes

    for protocol in (2, 3, 4, 5):
        np.testing.assert_array_equal(read_legacy_reward_bytes(pickle.dumps(REWARD, protocol=protocol)), REWARD)


# ------------------------------------------------------------------------ help topics
def test_help_topics_print_the_guides(capsys):
    assert cli.main(["--help", "trackmania"]) == 0
    text = capsys.readouterr().out
    assert "--install --env tm20lidar" in text and "--doctor" in text and "--worker --test" in text
    assert 'pip install ".[trackmania]"' in text
    assert cli.main(["--help", "config"]) == 0
    assert "OPENPLANET_FOLDER" in capsys.readouterr().out
    assert cli.main(["--help", "nonsense"]) == 2
    assert "trackmania, config" in capsys.readouterr().err
