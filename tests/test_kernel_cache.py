"""numba's cache of the compiled kernels is dropped whenever a kernel module changes
(`linalg.drop_stale_caches`): numba itself checks only each function's own file, so a
cached caller would keep the old code of a kernel edited in another file."""

import os
import subprocess
import sys
import textwrap

import numba
import pytest
from numba.core import types

from fusion_opt import core, linalg

STAMP = "fusion_opt-kernels.stamp"


def _write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))


def _tree(tmp_path):
    """A package with kernel files in two folders, one plain file, and a fake cache."""
    root = tmp_path / "pkg"
    _write(root / "k.py", "@jit\ndef f():\n    return 1\n")
    _write(root / "sub" / "m.py", "@jit\ndef g():\n    return 2\n")
    _write(root / "plain.py", "x = 1\n")
    return root


def _fake_cache(root):
    files = [root / "__pycache__" / "k.f-1.py311.nbi", root / "__pycache__" / "k.f-1.py311.1.nbc",
             root / "sub" / "__pycache__" / "m.g-1.py311.nbi"]
    for f in files:
        f.parent.mkdir(exist_ok=True)
        f.write_bytes(b"cached")
    pyc = root / "__pycache__" / "k.cpython-311.pyc"
    pyc.write_bytes(b"bytecode")
    return files, pyc


def test_a_changed_kernel_source_drops_every_cache_and_an_unchanged_tree_keeps_it(
        tmp_path, monkeypatch):
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")  # in-tree caches, NUMBA_CACHE_DIR set or not
    root = _tree(tmp_path)
    caches = {str(root / "__pycache__"), str(root / "sub" / "__pycache__")}
    files, pyc = _fake_cache(root)
    assert set(linalg.drop_stale_caches(str(root))) == caches  # no stamp yet: dropped
    assert not any(f.exists() for f in files) and pyc.exists()
    stamp = (root / "__pycache__" / STAMP).read_text()
    assert (root / "sub" / "__pycache__" / STAMP).read_text() == stamp

    files, _ = _fake_cache(root)
    assert linalg.drop_stale_caches(str(root)) == []  # unchanged: kept
    (root / "plain.py").write_text("x = 2\n")  # not a kernel module: kept
    assert linalg.drop_stale_caches(str(root)) == []
    assert all(f.exists() for f in files)

    (root / "sub" / "m.py").write_text("@jit\ndef g():\n    return 3\n")
    assert set(linalg.drop_stale_caches(str(root))) == caches  # both folders, not only sub's
    assert not any(f.exists() for f in files) and pyc.exists()
    new = (root / "__pycache__" / STAMP).read_text()
    assert new != stamp and (root / "sub" / "__pycache__" / STAMP).read_text() == new
    assert not list(root.rglob("*.tmp"))


def test_a_changed_kernel_of_a_linked_package_drops_the_callers_cache(tmp_path, monkeypatch):
    """A package whose kernels call another's (trackers' RBMCDA calls fusion_opt's
    Cholesky) names it as linked: an edit of the other's kernels drops the caller's cache
    (its cached code embeds them), and only the caller's."""
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    root, lib = _tree(tmp_path), tmp_path / "lib"
    _write(lib / "la.py", "@jit\ndef h():\n    return 4\n")
    lib_cache = lib / "__pycache__" / "la.h-1.py311.nbi"
    lib_cache.parent.mkdir()
    lib_cache.write_bytes(b"cached")
    assert linalg.drop_stale_caches(str(root), str(lib))  # no stamp yet
    files, _ = _fake_cache(root)
    assert linalg.drop_stale_caches(str(root), str(lib)) == []  # neither changed: kept
    (lib / "la.py").write_text("@jit\ndef h():\n    return 5\n")
    assert set(linalg.drop_stale_caches(str(root), str(lib))) == {
        str(root / "__pycache__"), str(root / "sub" / "__pycache__")}
    assert not any(f.exists() for f in files) and lib_cache.exists()
    assert linalg.drop_stale_caches(str(root), str(lib)) == []


def test_the_stamp_follows_numba_to_a_cache_outside_the_tree(tmp_path, monkeypatch):
    """Where numba caches elsewhere (NUMBA_CACHE_DIR here; the user-wide cache of a
    read-only install alike), the stamp and the dropping go there."""
    root = _tree(tmp_path)
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "user"))
    dropped = linalg.drop_stale_caches(str(root))
    assert len(dropped) == 2 and all(d.startswith(str(tmp_path / "user")) for d in dropped)
    assert all(os.path.exists(os.path.join(d, STAMP)) for d in dropped)
    assert not (root / "__pycache__").exists()


def test_a_cache_that_cannot_be_read_or_written_does_not_fail(tmp_path, monkeypatch):
    root = _tree(tmp_path)
    _fake_cache(root)
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setattr(linalg, "_cache_folder", lambda py_file: str(blocker))
    assert linalg.drop_stale_caches(str(root)) == []
    monkeypatch.undo()

    def refuse(*args):
        raise PermissionError("read-only")

    monkeypatch.setattr(linalg.os, "replace", refuse)  # a stamp that cannot be written
    monkeypatch.setattr(linalg.os, "remove", refuse)
    linalg.drop_stale_caches(str(root))
    assert not (root / "__pycache__" / STAMP).exists()


def test_processes_starting_at_once_do_not_fail(tmp_path):
    root = _tree(tmp_path)
    _fake_cache(root)
    code = f"from fusion_opt.linalg import drop_stale_caches; drop_stale_caches({str(root)!r})"
    procs = [subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE)
             for _ in range(6)]
    for p in procs:
        assert p.wait(timeout=60) == 0, p.stderr.read().decode()
    assert linalg.drop_stale_caches(str(root)) == []  # one consistent stamp left
    assert not list(root.rglob("*.tmp"))


BASE = """
    import os
    from numba import njit
    if not os.environ.get("NO_DROP"):
        from fusion_opt.linalg import drop_stale_caches
        drop_stale_caches(os.path.dirname(os.path.abspath(__file__)))
    jit = njit(cache=True)
"""


def _call(root, env=None):
    env = {**os.environ, "PYTHONPATH": str(root.parent), **(env or {})}
    out = subprocess.run([sys.executable, "-c", "import kpkg.outer; print(kpkg.outer.call())"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return int(out.stdout)


# drop=False shows numba's own hazard (3-4 s of compiles), not this package's code: with
# the slow tests
@pytest.mark.parametrize("drop", [pytest.param(False, marks=pytest.mark.slow), True])
def test_a_cached_caller_runs_the_edited_kernel(tmp_path, drop):
    """The hazard itself with numba's real cache: outer.call (cached) calls inner.value;
    after an edit of inner.py alone, numba on its own still runs the old value (drop=False:
    what happened to exact.fuse_exact), and with drop_stale_caches the new one."""
    root = tmp_path / "kpkg"
    _write(root / "__init__.py", "")
    _write(root / "base.py", BASE)
    _write(root / "inner.py", "from .base import jit\n@jit\ndef value():\n    return 1\n")
    _write(root / "outer.py", "from .base import jit\nfrom .inner import value\n"
                              "@jit\ndef call():\n    return value()\n")
    env = None if drop else {"NO_DROP": "1"}
    assert _call(root, env) == 1
    assert _call(root, env) == 1  # from the cache
    _write(root / "inner.py", "from .base import jit\n@jit\ndef value():\n    return 2\n")
    assert _call(root, env) == (2 if drop else 1)


def test_compile_part_refuses_an_unknown_part():
    with pytest.raises(ValueError, match="part must be one of"):
        core.compile_part("everything")


@pytest.mark.slow
def test_after_the_parts_compiled_by_other_processes_a_user_compiles_nothing(tmp_path):
    """What studies/runner.py and tests/conftest.py rely on: after other processes compiled
    the parts (`core.compile_part`, stage by stage) into a cold cache, the library's calls
    load every kernel from the cache: numba compiles nothing."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    part = "from fusion_opt import core; core.compile_part({!r})"
    for stage in core.KERNEL_STAGES:  # a stage's parts at once, as the runner does
        procs = [subprocess.Popen([sys.executable, "-c", part.format(name)], env=env)
                 for name in stage]
        assert [p.wait() for p in procs] == [0] * len(stage)
    calls = textwrap.dedent("""
        import numpy as np
        from numba.core import event
        compiled = []
        class Listener(event.Listener):
            def on_start(self, e):
                compiled.append(e.data["dispatcher"].py_func.__qualname__)
            def on_end(self, e):
                pass
        event.register("numba:compile", Listener())
        import fusion_opt as fo
        C = np.stack([np.eye(3) * (i + 1) for i in range(4)])
        M = np.arange(12.0).reshape(4, 3)
        for criterion in ("trace", "logdet"):
            fo.bci(M, C, criterion)
            fo.bci(M, C, criterion, "clarabel")
            for backend in ("newton", "closed-form"):
                fo.ci(M[0], C[0], M[1], C[1], criterion, backend)
        fo.mbci(M, C, p_detect=[0.9, 0.8, 0.7, 0.6], chi=0.9)
        fo.fuse_batch(M[None], C[None])
        for method in ("fast-ci", "ifci"):
            fo.fuse(M, C, method)
        fo.fuse(M[:2], C[:2], "ei")
        X = np.zeros((4, 4, 3, 3))
        X[range(4), range(4)] = C
        fo.fuse(M, C, "known-cross", cross=X)
        fo.optimality_gap(C, np.full(4, 0.25))
        e = fo.Estimates(np.zeros((2, 3)), C[:2])  # two reports of a source at one point
        fo.associate({0: e, 1: e}, 1.0)
        fo.ProcessingNode(["a", "b"], method="mbci", threshold=1.0,
                          p_detect={"a": 0.9, "b": 0.8}, chi=0.9).step({"a": e, "b": e})
        print(compiled)
    """)
    out = subprocess.run([sys.executable, "-c", calls], env=env, check=True,
                         capture_output=True, text=True).stdout
    assert out.strip() == "[]", out


class _Dispatcher:
    """Stands for a numba dispatcher: records the LLVM level each compile ran at."""

    def __init__(self, fn, fail=False):
        self.levels, self.sigs, self.fail = [], [], fail

    def compile(self, sig):
        self.levels.append(int(numba.core.config.OPT))
        self.sigs.append(sig)
        if self.fail:
            raise RuntimeError("typing failed")
        return sig


def test_kernels_compile_at_level_2_and_the_level_comes_back(monkeypatch):
    monkeypatch.delenv("NUMBA_OPT", raising=False)
    monkeypatch.setattr(numba.core.config, "OPT", type(numba.core.config.OPT)(3))
    kernel = linalg._at_level_2(_Dispatcher, None)(lambda: None)
    assert kernel.compile("sig") == "sig"
    failing = linalg._at_level_2(lambda fn: _Dispatcher(fn, fail=True), None)(lambda: None)
    with pytest.raises(RuntimeError, match="typing failed"):
        failing.compile("sig")
    assert kernel.levels == [2] and failing.levels == [2]
    assert int(numba.core.config.OPT) == 3


def test_a_level_the_user_set_in_numba_opt_is_kept(monkeypatch):
    monkeypatch.setenv("NUMBA_OPT", "1")
    monkeypatch.setattr(numba.core.config, "OPT", type(numba.core.config.OPT)(1))
    kernel = linalg._at_level_2(_Dispatcher, None)(lambda: None)
    kernel.compile("sig")
    assert kernel.levels == [1] and int(numba.core.config.OPT) == 1


def test_a_kernel_is_compiled_for_the_plain_types_of_constant_arguments():
    """A call from a kernel with a constant argument (types Literal[bool](True),
    Literal[int](0)) compiles the kernel for bool and int64, the types of the same call
    with variables, not a copy per constant."""
    kernel = linalg._at_level_2(_Dispatcher, None)(lambda: None)
    kernel.compile((types.literal(True), types.literal(0), types.float64))
    kernel.compile((types.boolean, types.int64, types.float64))
    assert kernel.sigs == [(types.boolean, types.int64, types.float64)] * 2


def _kernel(module: str):
    """A new uncached kernel whose function says it is of `module`."""
    def twice(x):
        return 2 * x
    twice.__module__ = module
    return numba.njit(cache=False)(twice)


def test_the_first_compile_of_a_package_kernel_is_told_once(caplog, monkeypatch):
    monkeypatch.setattr(linalg.NOTICE, "told", False)
    with caplog.at_level("WARNING", logger="fusion_opt"):
        _kernel("elsewhere")(1)  # not the package's: nothing to tell
        assert caplog.records == []
        ours = _kernel("fusion_opt.notice_test")
        ours(1)
        ours(1.5)  # a second compile, of another signature, is not told again
        _kernel("fusion_opt.notice_test")(2)
    assert [(r.name, r.levelname, r.getMessage()) for r in caplog.records] == [
        ("fusion_opt", "WARNING", linalg.COMPILE_NOTICE)]


def test_a_fusion_of_compiled_kernels_tells_nothing(caplog, monkeypatch):
    import fusion_opt as fo

    fo.warmup(2, 3)  # compiles the kernels (and says so) if they were not cached
    caplog.clear()
    monkeypatch.setattr(linalg.NOTICE, "told", False)
    with caplog.at_level("WARNING", logger="fusion_opt"):
        fo.bci([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], [[[1.0, 0.0], [0.0, 2.0]]] * 3)
    assert caplog.records == []


def test_the_notice_reaches_stderr_of_a_program_that_configures_no_logging(tmp_path):
    """With an empty cache, the first compile of a package kernel (here linalg.copy) says
    so on stderr; the second process, which loads it from the cache, says nothing."""
    code = "import numpy as np; from fusion_opt import linalg; linalg.copy(np.zeros(3), np.ones(3))"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                           text=True, timeout=300) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    assert runs[0].stderr.strip() == linalg.COMPILE_NOTICE
    assert runs[1].stderr == ""


@pytest.mark.slow
def test_every_kernel_indexes_within_its_arrays(tmp_path):
    """The default test suite passes with every kernel compiled under numba's bounds
    checking (NUMBA_BOUNDSCHECK=1, into a cache of its own), which turns an index past an
    array into an IndexError. numba does not check by default, so a kernel writing past a
    buffer would corrupt memory silently, and since `factored.work` carves its buffers
    from shared allocations, a neighbouring buffer of the same problem."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                          "-m", "not slow", "-n", "2", "tests"],
                         cwd=root, env=env, capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert " passed" in out.stdout.splitlines()[-1]


@pytest.mark.parametrize("damage", ["bytes", "fifo", "endless", "folder"])
def test_a_damaged_stamp_neither_fails_nor_blocks_the_import(tmp_path, damage, caplog):
    """fuzz9: a stamp of bytes that are not UTF-8 raised UnicodeDecodeError at every import,
    a FIFO there blocked it, a link to /dev/zero filled the memory; a folder there (which
    cannot be replaced) dropped the caches at every start without a word."""
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "k.f-1.py311.nbi").write_bytes(b"cached")
    stamp = cache / STAMP
    if damage == "bytes":
        stamp.write_bytes(b"\xff\xfe\x80garbage")
    elif damage == "fifo":
        os.mkfifo(stamp)
    elif damage == "endless":
        stamp.symlink_to("/dev/zero")
    else:
        stamp.mkdir()
    assert linalg._refresh(str(cache), "a" * 64)  # a mismatch: dropped
    assert not (cache / "k.f-1.py311.nbi").exists()
    if damage == "folder":
        assert "cannot write the stamp of the kernel cache" in caplog.text
    else:
        assert stamp.read_text() == "a" * 64 and not linalg._refresh(str(cache), "a" * 64)


GUARDED = """
    from fusion_opt.linalg import jit
    @jit
    def lower():
        return 1
    @jit
    def upper():
        return 2
    def call():
        return lower() * 10 + upper()
"""


def test_damaged_or_swapped_cache_entries_are_compiled_again(tmp_path):
    """fuzz9: a truncated index or code file raised numba's EOFError or UnpicklingError at
    every call, in every process, and code files swapped between two kernels of one
    signature ran each other's code."""
    root = tmp_path / "gpkg"
    _write(root / "__init__.py", "")
    _write(root / "two.py", GUARDED)
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "NUMBA_CACHE_DIR": str(tmp_path / "nc")}
    run = [sys.executable, "-c", "import gpkg.two; print(gpkg.two.call())"]

    def call():
        out = subprocess.run(run, env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        return int(out.stdout)

    assert call() == 12
    files = {p.name: p for p in (tmp_path / "nc").rglob("two.*.nb?")}
    code = {k: sorted(p for n, p in files.items() if f"two.{k}-" in n and n.endswith(".nbc"))[0]
            for k in ("lower", "upper")}
    a, b = code["lower"].read_bytes(), code["upper"].read_bytes()
    code["lower"].write_bytes(b)
    code["upper"].write_bytes(a)
    assert call() == 12  # swapped: each compiled again, not run as the other
    index = sorted(p for n, p in files.items() if "two.lower-" in n and n.endswith(".nbi"))[0]
    index.write_bytes(index.read_bytes()[:10])
    assert call() == 12
    assert call() == 12  # and cached again


def test_without_a_cache_folder_the_kernels_compile_uncached(monkeypatch, caplog):
    """fuzz9: a read-only install whose user has no writable HOME and no NUMBA_CACHE_DIR
    could not import the package (numba's "cannot cache function ...: no locator
    available" at every kernel's decoration)."""
    def no_locator(fn):
        raise RuntimeError(f"cannot cache function {fn.__name__!r}: no locator available")

    monkeypatch.setattr(linalg, "_UNCACHED", [])

    @linalg._at_level_2(no_locator, numba.njit(error_model="numpy"))
    def twice(x):
        return 2.0 * x

    assert twice(1.5) == 3.0
    assert "numba cannot cache the kernels" in caplog.text


def test_a_relative_cache_folder_is_the_one_of_the_import(tmp_path):
    """fuzz9: with a relative NUMBA_CACHE_DIR numba loads from the folder current at each
    call; a program that changed folder after the import ran kernels the stale-cache check
    had not looked at."""
    code = "import fusion_opt, numba; print(numba.core.config.CACHE_DIR)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120,
                         env={**os.environ, "NUMBA_CACHE_DIR": "rel"}, check=True)
    assert out.stdout.strip() == str(tmp_path / "rel")
