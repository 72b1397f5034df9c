"""JAX's persistent compilation cache, on by default for every ``jaxcr`` command.

XLA compilation of the refinement, the CTR solver or the stereo pipeline takes tens of seconds
per process; with the persistent cache a second process with the same shapes and settings
loads the compiled executables from disk instead. :func:`enable_compile_cache` is called once
by :func:`jaxcr.cli.main` before any command runs (library users may call it themselves).

Where and whether (first match wins):

- ``enable_compile_cache(path=...)``: that folder (``False`` turns the cache off);
- ``JAXCR_COMPILE_CACHE``: ``0`` (or off/false/no) turns it off, ``1`` (on/true/yes), ``auto``
  or unset leaves it on; any other value is an :class:`~jaxcr.errors.InputError` (exit 2);
- ``JAXCR_CACHE_DIR``: the cache folder; empty turns the cache off (as did the older
  ``JAXCR_JAX_CACHE``, still honoured when ``JAXCR_CACHE_DIR`` is unset);
- default: ``$XDG_CACHE_HOME/jaxcr/jax``, else ``~/.cache/jaxcr/jax``.

A folder that cannot be created or written is not an error: one warning (on the ``jaxcr``
logger, printed on stderr), and the command runs on without the cache (it only costs compile time).
"""

from __future__ import annotations

import logging
import os
import tempfile

from jaxcr.errors import InputError

# warnings go to the "jaxcr" logger: the CLI prints them on stderr (jaxcr.cli.main), and a
# library user without logging configured sees them on stderr too (logging.lastResort)
_log = logging.getLogger(__name__)

ENV_SWITCH = "JAXCR_COMPILE_CACHE"
ENV_DIR = "JAXCR_CACHE_DIR"
ENV_DIR_LEGACY = "JAXCR_JAX_CACHE"
_ON = ("1", "on", "true", "yes", "", "auto")
_OFF = ("0", "off", "false", "no")
#: compilations at least this long are stored. 0: everything, also the small eager ops and
#: glue programs of a command (each costs ~10-100 ms to compile under load and a few ms to
#: load), so that a second process compiles as little as possible.
MIN_COMPILE_TIME_S = 0.0
#: entries at least this large (bytes) are stored; 0 = all (JAX's CPU default is also 0).
MIN_ENTRY_SIZE_BYTES = 0

_warned: set[str] = set()
_enabled: str | None = None


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/jaxcr/jax`` if XDG_CACHE_HOME is set (and absolute), else
    ``~/.cache/jaxcr/jax``."""
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = xdg if os.path.isabs(xdg) else os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxcr", "jax")


def cache_switch(env: str | None = None) -> bool:
    """Whether ``JAXCR_COMPILE_CACHE`` (or ``env``) leaves the cache on. Raises
    :class:`~jaxcr.errors.InputError` for a value other than 0/1/auto and their synonyms."""
    value = os.environ.get(ENV_SWITCH, "") if env is None else env
    v = value.strip().lower()
    if v in _ON:
        return True
    if v in _OFF:
        return False
    raise InputError(f"environment variable {ENV_SWITCH}: expected 0, 1 or auto, got {value!r}")


def resolve_cache_dir(path: str | os.PathLike | bool | None = None) -> str | None:
    """The cache folder the rules of this module select, or None when the cache is off."""
    if path is False:
        return None
    on = cache_switch()  # checked even with an explicit path: a bad value is always an error
    if path is not None and path is not True:
        return os.fspath(path)
    if not on:
        return None
    for name in (ENV_DIR, ENV_DIR_LEGACY):
        if name in os.environ:
            value = os.environ[name].strip()
            return os.path.expanduser(value) if value else None
    return default_cache_dir()


def _warn_once(path: str, why: str) -> None:
    if path in _warned:
        return
    _warned.add(path)
    _log.warning(
        "jaxcr: warning: compilation cache %s: %s; running without it "
        "(set %s to a writable folder, or %s=0 to silence this)",
        path, why, ENV_DIR, ENV_SWITCH,
    )  # fmt: skip


def _writable(path: str) -> str | None:
    """None if ``path`` is (made) a writable folder, else the reason it is not."""
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".jaxcr-probe-", dir=path)
        os.close(fd)
        os.remove(probe)
    except OSError as err:
        return err.strerror or str(err)
    return None


def _disable() -> None:
    """Turn off a cache an earlier call of this process turned on (JAX's own setting alone
    is left as it is)."""
    global _enabled
    if _enabled is None:
        return
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    jax.config.update("jax_compilation_cache_dir", None)
    cc.reset_cache()
    _enabled = None


def enable_compile_cache(*, path: str | os.PathLike | bool | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache; returns the folder, or None when it is off
    (switched off, or the folder is not writable: then one warning on stderr).

    Call it before the first compilation of the process; later calls with the same folder do
    nothing.

    Parameters
    ----------
    path : str, os.PathLike, bool or None
        the cache folder; None: ``JAXCR_CACHE_DIR`` or the per-user default
        (``$XDG_CACHE_HOME/jaxcr/jax`` or ``~/.cache/jaxcr/jax``); False: off.

    Returns
    -------
    str or None
        the absolute folder in use, or None when the cache is off.

    Raises
    ------
    InputError
        for a bad ``JAXCR_COMPILE_CACHE`` value.

    Examples
    --------
    >>> import jaxcr as jcr
    >>> jcr.enable_compile_cache(path=False) is None  # off (e.g. in a benchmark)
    True
    >>> jcr.enable_compile_cache()  # doctest: +SKIP
    '/home/me/.cache/jaxcr/jax'
    """
    global _enabled
    folder = resolve_cache_dir(path)
    if folder is None:
        _disable()
        return None
    folder = os.path.abspath(folder)
    if folder == _enabled:
        return folder
    why = _writable(folder)
    if why is not None:
        _warn_once(folder, why)
        _disable()
        return None
    import jax

    try:
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", MIN_ENTRY_SIZE_BYTES)
    except AttributeError:  # a JAX without these options: just compile
        return None
    # JAX opens (or, with no folder set, rules out) its cache at the first compilation of the
    # process; let it reopen at the next one, in case something compiled before this call
    from jax.experimental.compilation_cache import compilation_cache as cc

    cc.reset_cache()
    _enabled = folder
    return folder
