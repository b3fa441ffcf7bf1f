"""tmrl.util: partial (with the nested-default rule), partial_to_dict, prod, cached_property,
atomic writes, dump/load."""

from __future__ import annotations

import functools
import os
import pickle
import subprocess
import sys
import threading

import numpy as np
import pytest

from tmrl import util
from tmrl.util import cached_property, partial, partial_to_dict, prod


class Memory:
    def __init__(self, memory_size: int = 100, batch_size: int = 8, device: str = "cpu"):
        self.memory_size, self.batch_size, self.device = memory_size, batch_size, device


class Agent:
    def __init__(self, lr: float = 0.1, gamma: float = 0.99):
        self.lr, self.gamma = lr, gamma


def make_trainer(memory_cls=Memory, agent_cls=partial(Agent, lr=0.5), epochs: int = 10, env=None):  # noqa: B008
    return memory_cls(), agent_cls(), epochs


# --- partial -------------------------------------------------------------------------------------


def test_partial_is_functools_partial():
    p = partial(Memory, memory_size=5)
    assert isinstance(p, functools.partial)
    assert p(batch_size=2).memory_size == 5 and p(batch_size=2).batch_size == 2


def test_bare_nested_partial_takes_the_callees_default_as_function():
    p = partial(make_trainer, memory_cls=partial(batch_size=64))
    assert p.keywords["memory_cls"].func is Memory
    memory, agent, epochs = p()
    assert (memory.memory_size, memory.batch_size) == (100, 64)
    assert agent.lr == 0.5 and epochs == 10


def test_bare_nested_partial_extends_a_default_that_is_itself_a_partial():
    p = partial(make_trainer, agent_cls=partial(gamma=0.5))
    _, agent, _ = p()
    assert (agent.lr, agent.gamma) == (0.5, 0.5)


def test_bare_partial_nested_two_levels():
    def outer(trainer=make_trainer):
        return trainer()

    memory, _, _ = partial(outer, trainer=partial(memory_cls=partial(device="cuda")))()
    assert memory.device == "cuda"


def test_bare_partial_for_a_parameter_without_default_is_refused():
    def f(x, y=1):
        return x

    with pytest.raises(TypeError, match="'x' has no default"):
        partial(f, x=partial(a=1))
    with pytest.raises(TypeError, match="'z' has no default"):
        partial(f, z=partial(a=1))


def test_non_bare_nested_partials_are_left_alone():
    inner = partial(Memory, memory_size=3)
    p = partial(make_trainer, memory_cls=inner)
    assert p.keywords["memory_cls"] is inner


def test_bare_partial_itself_cannot_be_called():
    with pytest.raises(ValueError, match="placeholder"):
        partial(a=1)()


# --- partial_to_dict -----------------------------------------------------------------------------


def test_partial_to_dict_lists_every_parameter_and_nests():
    d = partial_to_dict(partial(make_trainer, memory_cls=partial(batch_size=64), epochs=3))
    assert d["__format_version__"] == "3"
    assert d["__class__"].endswith("make_trainer")
    assert d["epochs"] == 3 and d["env"] is None
    assert d["memory_cls"]["__class__"].endswith("Memory")
    assert d["memory_cls"]["batch_size"] == 64 and d["memory_cls"]["memory_size"] == 100
    assert "__format_version__" not in d["memory_cls"]
    assert d["agent_cls"]["lr"] == 0.5 and d["agent_cls"]["gamma"] == 0.99


def test_partial_to_dict_refuses_positional_and_unknown_arguments():
    with pytest.raises(ValueError, match="keyword"):
        partial_to_dict(functools.partial(Memory, 5))
    with pytest.raises(ValueError, match="does not take"):
        partial_to_dict(functools.partial(Memory, colour="red"))


def test_partial_to_dict_accepts_extra_keywords_for_var_kwargs():
    def f(a=1, **kwargs):
        return a

    assert partial_to_dict(functools.partial(f, b=2))["b"] == 2


# --- prod ----------------------------------------------------------------------------------------


def test_prod():
    assert prod([]) == 1
    assert prod((2, 3, 4)) == 24
    assert prod(np.array([2, 5]).tolist(), start=3) == 30
    assert prod(iter([1.5, 2])) == 3.0


# --- cached_property -----------------------------------------------------------------------------


class Counter:
    calls = 0

    def __init__(self, base: int):
        self.base = base

    @cached_property
    def doubled(self) -> int:
        """Twice the base."""
        Counter.calls += 1
        return self.base * 2

    tripled = cached_property(lambda self: self.base * 3)


def test_cached_property_computes_once_per_instance():
    Counter.calls = 0
    a, b = Counter(1), Counter(5)
    assert (a.doubled, a.doubled, b.doubled) == (2, 2, 10)
    assert Counter.calls == 2
    assert a.tripled == 3 and b.tripled == 15


def test_cached_property_recomputes_after_delete_and_can_be_set():
    Counter.calls = 0
    c = Counter(2)
    assert c.doubled == 4
    c.base = 10
    assert c.doubled == 4
    del c.doubled
    assert c.doubled == 20 and Counter.calls == 2
    c.doubled = 7
    assert c.doubled == 7


def test_cached_property_on_the_class_is_the_descriptor():
    assert isinstance(Counter.doubled, cached_property)
    assert Counter.doubled.__doc__ == "Twice the base."


# --- atomic writes -------------------------------------------------------------------------------


def test_atomic_write_creates_parents_and_replaces(tmp_path):
    path = tmp_path / "a" / "b" / "file.bin"
    assert util.atomic_write_bytes(path, b"one") == path
    assert path.read_bytes() == b"one"
    util.atomic_write_bytes(path, memoryview(b"two"))
    assert path.read_bytes() == b"two"
    util.atomic_write_text(path, "héllo")
    assert path.read_text(encoding="utf-8") == "héllo"
    assert sorted(p.name for p in path.parent.iterdir()) == ["file.bin"]


def test_failed_atomic_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "weights.tmod"
    path.write_bytes(b"old")
    with pytest.raises(TypeError):
        util.atomic_write_bytes(path, 12345)  # not bytes: the write fails midway
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["weights.tmod"]


def test_concurrent_atomic_writes_never_mix(tmp_path):
    path = tmp_path / "f"
    payloads = [bytes([i]) * 200_000 for i in range(8)]
    threads = [threading.Thread(target=util.atomic_write_bytes, args=(path, p)) for p in payloads]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert path.read_bytes() in payloads
    assert os.listdir(tmp_path) == ["f"]


# --- dump / load ---------------------------------------------------------------------------------


def test_dump_load_round_trip(tmp_path):
    obj = {"obs": (np.arange(6, dtype=np.float32).reshape(2, 3), [1, 2.5, None]), "name": "x", "b": b"\x00"}
    path = util.dump(obj, tmp_path / "d" / "sample.bin")
    back = util.load(path)
    np.testing.assert_array_equal(back["obs"][0], obj["obs"][0])
    assert back["obs"][0].dtype == np.float32
    assert list(back["obs"][1]) == [1, 2.5, None]
    assert back["name"] == "x" and back["b"] == b"\x00"


def test_load_refuses_a_pickle(tmp_path):
    from tmrl.wire import DecodeError

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(DecodeError):
        util.load(path)


def test_partial_to_dict_names_builtin_defaults_it_cannot_inspect():
    def f(container=dict, n=2):
        return n

    d = partial_to_dict(functools.partial(f))
    assert d["container"] == "builtins:dict" and d["n"] == 2


@pytest.mark.posix  # file modes
def test_atomic_write_uses_ordinary_permissions_unless_asked(tmp_path):
    import os
    import stat

    from tmrl.util import atomic_write_bytes

    mask = os.umask(0o022)
    os.umask(mask)
    plain = atomic_write_bytes(tmp_path / "weights.tmod", b"w")
    secret = atomic_write_bytes(tmp_path / "key.pem", b"k", mode=0o600)
    assert stat.S_IMODE(plain.stat().st_mode) == 0o666 & ~mask
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_dump_load_round_trip_gives_writable_arrays(tmp_path):
    import numpy as np

    from tmrl.util import dump, load

    obj = {"a": np.arange(1000, dtype=np.float32), "t": (1, "x", None)}
    dump(obj, tmp_path / "obj.bin")
    back = load(tmp_path / "obj.bin")
    assert back["t"] == (1, "x", None)
    np.testing.assert_array_equal(back["a"], obj["a"])
    back["a"][0] = 5.0  # a read-only view would raise here
    assert back["a"].flags.writeable


_FAULTS_CHILD = r"""
import resource, sys
import numpy as np
import torch
tune = sys.argv[1]
if tune == "util":
    from tmrl.util import reuse_freed_memory
    assert reuse_freed_memory() and reuse_freed_memory()
elif tune == "trainer":
    import gymnasium
    from tmrl import util
    from tmrl.memory import GenericTorchMemory
    from tmrl.training import TrainingAgent
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial
    assert not util._malloc_tuned
    space = gymnasium.spaces.Box(-1, 1, (2,), np.float32)
    class Agent(TrainingAgent):
        def train(self, batch): return {}
        def get_actor(self): return None
    TorchTrainingOffline(env_cls=(space, space), memory_cls=partial(GenericTorchMemory),
                         training_agent_cls=Agent, device="cpu")
    assert util._malloc_tuned
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):  # the heap settles: freed blocks coalesce into ones the next request fits
    a = torch.ones(12 << 20)
    del a
f0 = faults()
for _ in range(10):
    a = torch.ones(12 << 20)  # 48 MiB (as one CNN activation), every page written
    del a
print(faults() - f0)
"""


@pytest.mark.linux  # glibc's allocator settings, counted in page faults by the resource module
@pytest.mark.skipif(sys.platform.startswith("linux") and not os.confstr("CS_GNU_LIBC_VERSION"),
                    reason="the allocator settings exist with glibc only")
def test_reuse_freed_memory_stops_page_faults_of_repeated_large_allocations_and_the_trainer_applies_it():
    def faults(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", _FAULTS_CHILD, mode], capture_output=True, text=True,
                             timeout=120, check=True)
        return int(out.stdout.split()[-1])

    default, tuned, trainer = faults("none"), faults("util"), faults("trainer")
    # glibc's default maps blocks above 32 MiB afresh: each round faults its 12,288 pages in again.
    assert default > 10 * 12_288 * 0.9
    assert tuned < default / 20
    assert trainer < default / 20


def test_reuse_freed_memory_is_not_applied_on_import():
    out = subprocess.run([sys.executable, "-c", "import tmrl, tmrl.util, tmrl.training_offline; "
                          "print(tmrl.util._malloc_tuned)"], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
