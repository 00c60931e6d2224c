"""mccnn_cl.atomic's temporary files in a folder that several machines share (an NFS
home directory holds ~/.cache/mccnn_cl): a pid tells whether a writer of this
machine runs, nothing of another machine's."""

import os
import signal
import subprocess
import sys
import time

from mccnn_cl import atomic
from mccnn_cl.atomic import PREFIX

#: a writer on another machine: this host's name faked before mccnn_cl.atomic names its file,
#: killed (SIGKILL) in the middle of its write, so its temporary file stays
ELSEWHERE = ("import os, signal, socket, sys\n"
             "socket.gethostname = lambda: 'node-7.cluster.example.org'\n"
             "from mccnn_cl import atomic\n"
             "def boom(tmp):\n"
             "    open(tmp, 'wb').write(b'partial')\n"
             "    os.kill(os.getpid(), signal.SIGKILL)\n"
             "atomic.atomic_write(sys.argv[1], boom)\n")


def temps(folder):
    return sorted(f for f in os.listdir(folder) if f.startswith(PREFIX))


def age(path, seconds):
    t = time.time() - seconds
    os.utime(path, (t, t))


def test_another_hosts_temporary_file_is_kept_until_old(tmp_path):
    """A temporary file written from another host (its pid runs nowhere here, which says
    nothing of that host) is a write that may be in progress there: the writes of this
    host keep it while it is young (before: removed at once, its writer's rename then
    failed) and remove it once unchanged for atomic.STALE_SECONDS (its writer died).
    An older version's name (``.mccnn-tmp-<pid>-…``, no host) is treated the same."""
    p = subprocess.Popen([sys.executable, "-c", ELSEWHERE, str(tmp_path / "cloud.ply")])
    assert p.wait(timeout=60) == -signal.SIGKILL
    [theirs] = temps(tmp_path)
    older = f"{PREFIX}{p.pid}-abcdefgh.ply"  # an older version's name, from whichever host
    (tmp_path / older).write_bytes(b"partial")

    atomic.atomic_write_bytes(tmp_path / "a.bin", b"a")
    assert temps(tmp_path) == sorted([theirs, older])  # young: kept though their pid does not run here
    assert atomic.parse_temp_name(theirs) == ("node-7-cluster-example-org", p.pid)
    age(tmp_path / theirs, atomic.STALE_SECONDS - 120)
    age(tmp_path / older, atomic.STALE_SECONDS - 120)
    atomic.atomic_write_bytes(tmp_path / "b.bin", b"b")
    assert temps(tmp_path) == sorted([theirs, older])  # not yet old enough

    age(tmp_path / theirs, atomic.STALE_SECONDS + 60)
    atomic.atomic_write_bytes(tmp_path / "c.bin", b"c")
    assert temps(tmp_path) == [older]
    age(tmp_path / older, atomic.STALE_SECONDS + 60)
    assert atomic.remove_stale(tmp_path) == [str(tmp_path / older)]
    assert sorted(os.listdir(tmp_path)) == ["a.bin", "b.bin", "c.bin"]


def test_this_hosts_dead_writer_is_removed_at_once(tmp_path):
    """This host's dead writer's file goes at once, young or not; a running writer's stays,
    however old; a file of the same pid on another host is no news of either."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    mine_dead = f"{atomic.temp_prefix(dead.pid)}x.ply"
    mine_alive = f"{atomic.temp_prefix()}y.ply"  # this process: running
    theirs = f"{atomic.temp_prefix(dead.pid, atomic.host_tag('not-' + atomic.host_tag()))}z.ply"
    for name in (mine_dead, mine_alive, theirs):
        (tmp_path / name).write_bytes(b"x")
    age(tmp_path / mine_alive, 10 * atomic.STALE_SECONDS)
    assert atomic.remove_stale(tmp_path) == [str(tmp_path / mine_dead)]
    assert temps(tmp_path) == sorted([mine_alive, theirs])


def test_host_names_in_temporary_names_are_safe_and_bounded():
    """The host part holds letters, digits and dashes only, at most HOST_TAG_MAX of them, and
    reads back whatever the host's name (dots, dashes, digits, other scripts, a long FQDN)."""
    assert atomic.host_tag("node-1.cluster.example.org") == "node-1-cluster-example-org"
    assert atomic.host_tag("") == "unknown" and atomic.host_tag("a/b c\\d\0e") == "a-b-c-d-e"
    assert atomic.host_tag("höst") == "h-st"
    long1, long2 = "n" * 60 + ".one.example.org", "n" * 60 + ".two.example.org"
    assert len(atomic.host_tag(long1)) == atomic.HOST_TAG_MAX and atomic.host_tag(long1) != atomic.host_tag(long2)
    for host in ("node-1.cluster.example.org", "123", "a-1-2", long1, "höst", ""):
        tag = atomic.host_tag(host)
        assert set(tag) <= set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-"), tag
        name = f"{atomic.temp_prefix(4242, tag)}q_8xyz12.3-4.ply"
        assert atomic.parse_temp_name(name) == (tag, 4242)
    assert atomic.parse_temp_name(f"{PREFIX}4242-abcdefgh.ply") is None  # an older version's name
    assert atomic.parse_temp_name(".tmp-abc") is None and atomic.parse_temp_name("cloud.ply") is None
    assert atomic.parse_temp_name(atomic.temp_prefix() + "x") == (atomic.host_tag(), os.getpid())


def test_the_folders_other_files_are_left_alone(tmp_path):
    """Only files named as atomic's temporary files are removed: not the caches' older
    ``.tmp-*`` (binaries and tune_cache remove those in their own folders), nor a link or
    a folder named like a temporary file."""
    legacy = tmp_path / ".tmp-abc"
    legacy.write_bytes(b"x")
    age(legacy, 10 * atomic.STALE_SECONDS)
    folder = tmp_path / f"{atomic.temp_prefix(2 ** 22 + 1)}dir"
    folder.mkdir()
    link = tmp_path / f"{atomic.temp_prefix(2 ** 22 + 1)}link"
    link.symlink_to(legacy)
    assert atomic.remove_stale(tmp_path) == []
    assert sorted(os.listdir(tmp_path)) == sorted([legacy.name, folder.name, link.name])
