"""The persistent compilation cache (rdher_jax.compile_cache): keyed by host and config."""

import warnings

import jax
import pytest

from rdher_jax import compile_cache
from rdher_jax.config import parse_args, resolve
from rdher_jax.executor import build
from rdher_jax.program import hparams_from_config

TINY = ["env=FetchReach", "hidden=16", "layers=1", "batch_size=16", "n_batches=2",
        "buffer_size=1000", "n_test_rollouts=2", "n_cycles=1"]


def test_host_key_names_cpu_model_and_flags():
    base = compile_cache.host_key(("AMD EPYC 9R14", "avx2 avx512f sse4_2"))
    assert base == compile_cache.host_key(("AMD EPYC 9R14", "avx2 avx512f sse4_2"))
    # Another CPU, or the same model without AVX-512 (a VM that hides it), is another directory:
    # its cached native code is never loaded here.
    assert base != compile_cache.host_key(("Intel Xeon 8375C", "avx2 avx512f sse4_2"))
    assert base != compile_cache.host_key(("AMD EPYC 9R14", "avx2 sse4_2"))
    assert compile_cache.cache_dir("/r").parent.as_posix() == "/r"
    assert compile_cache.cache_dir("/r").name == f"xla-{compile_cache.host_key()}"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh cache directory for this test; JAX's cache settings are restored after it."""
    before = {k: getattr(jax.config, k) for k in (
        "jax_enable_compilation_cache", "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs", "jax_compilation_cache_max_size")}
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path))
    path = compile_cache.configure(True, min_compile_secs=0.0)
    yield path
    from jax.experimental.compilation_cache import compilation_cache as cc
    for k, v in before.items():
        jax.config.update(k, v)
    cc.reset_cache()


def entries(path, prefix="jit_"):
    """The cache's entries of programs named ``prefix...`` (min_compile_secs=0 also writes
    the little programs building a state makes)."""
    return sorted(p.name for p in path.iterdir()
                  if p.name.startswith(prefix) and p.name.endswith("-cache"))


def compile_init(args) -> int:
    """Compile (or load) the trainer's init program of ``args``; the persistent cache's hits."""
    from jax._src import monitoring

    jax.clear_caches()  # the in-memory cache would answer before the persistent one
    cfg = resolve(parse_args(TINY + args))
    _, program = build(cfg)
    lowered = jax.jit(program.init).lower(jax.random.PRNGKey(0), hparams_from_config(cfg))
    hits = []

    def listen(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    monitoring.register_event_listener(listen)
    try:
        lowered.compile()
    finally:
        monitoring.unregister_event_listener(listen)
    return len(hits)


def test_a_changed_config_compiles_anew_and_the_same_one_loads(cache):
    assert cache is not None and cache.is_dir() and entries(cache) == []
    assert compile_init(["hidden=16"]) == 0
    first = entries(cache, "jit_init")
    assert len(first) == 1, first  # init holds no host callback: it is written
    assert compile_init(["hidden=16"]) == 1  # the same program: loaded
    assert entries(cache, "jit_init") == first
    assert compile_init(["hidden=24"]) == 0  # another config: compiled anew, another entry
    assert len(entries(cache, "jit_init")) == 2


def test_off_writes_nothing(tmp_path, monkeypatch, cache):
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path / "off"))
    assert compile_cache.configure(False) is None
    compile_init(["hidden=20"])
    assert not (tmp_path / "off").exists()
    assert entries(cache) == []


@pytest.mark.parametrize("call", ["callback", "ffi"])
def test_only_ffi_physics_programs_are_written(cache, call):
    """With ``physics_call=callback`` the native backend's rollout holds a host callback: JAX
    refuses to cache it (and so never loads one process's callback pointer into another).
    The FFI handlers are named, not pointed to: that rollout is written (and another process
    loads it: tests/test_native_ffi.py)."""
    from rdher_jax.envs import native_ffi

    if call == "ffi" and native_ffi.library() is None:
        pytest.skip("the FFI handlers could not be built here")
    jax.clear_caches()
    cfg = resolve(parse_args(TINY + ["backend=mujoco", f"physics_call={call}"]))
    _, program = build(cfg)
    hp = hparams_from_config(cfg)
    ts = jax.jit(program.init)(jax.random.PRNGKey(0), hp)
    assert entries(cache, "jit_init")  # (the cache is on)
    jax.jit(program.collect).lower(ts, hp).compile()
    assert len(entries(cache, "jit_collect")) == (call == "ffi")


def test_an_entry_without_its_access_time_does_not_break_later_writes(tmp_path, monkeypatch):
    """JAX's eviction reads every entry's -atime file; an entry left without one (its writer
    killed between the two files) made every later write fail. configure() repairs it."""
    root = tmp_path / "root"
    orphan = compile_cache.cache_dir(root) / "jit_old-0123-cache"
    orphan.parent.mkdir(parents=True)
    orphan.write_bytes(b"x" * 10)
    monkeypatch.setenv(compile_cache.ENV_VAR, str(root))
    before = {k: getattr(jax.config, k) for k in (
        "jax_enable_compilation_cache", "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs", "jax_compilation_cache_max_size")}
    try:
        path = compile_cache.configure(True, min_compile_secs=0.0)
        atime = path / "jit_old-0123-atime"
        assert atime.exists()
        assert int.from_bytes(atime.read_bytes(), "little") == orphan.stat().st_mtime_ns
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # JAX warns, not raises, when a write fails
            compile_init(["hidden=20"])
        assert len(entries(path, "jit_init")) == 1
    finally:
        from jax.experimental.compilation_cache import compilation_cache as cc
        for k, v in before.items():
            jax.config.update(k, v)
        cc.reset_cache()
