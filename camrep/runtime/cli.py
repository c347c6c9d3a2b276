"""One command-line grammar for every `python -m camrep.*` tool: absl flags, `--config.` overrides
of an ml_collections config where the tool has one, and one set of exit codes.

Exit status, the same for every tool:

  0  done (a training run also when stopped by SIGTERM / Ctrl-C after saving a checkpoint), and
     `--help` / `--helpfull`
  1  a bug in camrep: a Python traceback (please report it)
  2  a user's mistake or a resource the run cannot use, on one `error: ...` line (the first line
     of the message names the flag, field, file or directory; more lines may follow): a bad
     flag, an unknown `--config.` field, a value of the wrong type, enum or sign, a config whose
     parts do not fit, a workdir or dataset that cannot be used, an unusable checkpoint, a full
     disk or a read-only file system, a file where a directory is needed, a missing
     `--flagfile`, a `JAX_PLATFORMS` the machine cannot start
  3  a training run stopped on non-finite values (the last checkpoint is kept; a resume verifies it)

Usage in a tool's module, either with flags defined at import (camrep.main, camrep.regression):

  def main(argv): ...            # raises ConfigError, WorkdirError, DataError, ... on bad input
  if __name__ == "__main__":
    cli.run(main)

or with flags defined by a function, so that the tool also runs in-process on its own
`FlagValues` (`main(argv) -> exit status`, for tests and notebooks; evaluate, prepare, show,
oracle):

  def define_flags(fv, argv): flags.DEFINE_string("out", None, "...", flag_values=fv) ...
  def run_cli(fv): ...           # reads fv.out; returns the exit status (None: 0)
  def main(argv=None): return cli.call(define_flags, run_cli, argv)
  if __name__ == "__main__":
    cli.main(define_flags, run_cli)

A user error's message is printed as `error: MESSAGE` on stderr, nothing else: no traceback.
"""

from __future__ import annotations

import errno
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn

from absl import app, flags, logging

EXIT_OK = 0
EXIT_BUG = 1
EXIT_USER = 2
EXIT_NON_FINITE = 3

_CONFIG_FLAGS = ("config",)
_HELP = ("--help", "-h", "-?", "--helpshort", "--helpfull")
# OSErrors that a user's machine causes, not a bug: the disk, the file system, permissions.
RESOURCE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


class UsageError(ValueError):
  """A flag or flag combination the tool refuses (raised before any work starts)."""


def _user_error_types() -> tuple[type[BaseException], ...]:
  """The exception types that are a user's mistake. Only modules already imported can have
  raised one, so the tools that never load Orbax do not import it here."""
  # FileNotFoundError: a path the user named (workdir, config.json, checkpoint) is missing.
  types: list[type[BaseException]] = [UsageError, app.UsageError, FileNotFoundError]
  for module, names in (
    ("camrep.runtime.runconfig", ("ConfigError",)),
    ("camrep.runtime.workdir", ("WorkdirError",)),
    ("camrep.runtime.checkpoint", ("CheckpointError",)),
    ("camrep.data.errors", ("DataError",)),
  ):
    m = sys.modules.get(module)
    types += [getattr(m, n) for n in names if m is not None and hasattr(m, n)]
  return tuple(types)


def resource_error(exc: BaseException) -> OSError | None:
  """The OSError of a full disk, a read-only file system or a permission in `exc`'s chain."""
  seen = set()
  while exc is not None and id(exc) not in seen:
    seen.add(id(exc))
    if isinstance(exc, OSError) and exc.errno in RESOURCE_ERRNOS:
      return exc
    exc = exc.__cause__ or exc.__context__
  return None


# OSErrors of a path that names the wrong kind of thing (a file where a directory is needed).
PATH_ERRNOS = (errno.ENOTDIR, errno.EISDIR, errno.EEXIST)


def path_error(exc: BaseException) -> str | None:
  """'PATH: ...' for an OSError in `exc`'s chain about a path of the wrong kind (a file where a
  directory was needed, e.g. `--data_dir` or `data.cache_dir` naming a file), or None."""
  seen = set()
  while exc is not None and id(exc) not in seen:
    seen.add(id(exc))
    if isinstance(exc, OSError) and exc.errno in PATH_ERRNOS and exc.filename:
      what = {
        errno.ENOTDIR: "is a file (or lies under one), where a directory is needed",
        errno.EISDIR: "is a directory, where a file is needed",
        errno.EEXIST: "already exists and is not a directory",
      }[exc.errno]
      return f"{exc.filename}: {what} ({exc.strerror or os.strerror(exc.errno)})"
    exc = exc.__cause__ or exc.__context__
  return None


_JAX_BACKEND_TEXT = ("Unable to initialize backend", "Unknown backend", "no platforms that are")


def jax_backend_error(exc: BaseException) -> str | None:
  """The `error:` message for JAX failing to start the platform `JAX_PLATFORMS` names (e.g.
  `gpu` on a machine without one), or None when `exc` is something else."""
  seen = set()
  while exc is not None and id(exc) not in seen:
    seen.add(id(exc))
    if isinstance(exc, RuntimeError) and any(t in str(exc) for t in _JAX_BACKEND_TEXT):
      platforms = os.environ.get("JAX_PLATFORMS", "")
      first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
      return (
        f"JAX_PLATFORMS={platforms!r}: JAX cannot start that platform on this machine ({first}); "
        "unset JAX_PLATFORMS to use what the machine has, or set JAX_PLATFORMS=cpu"
      )
    exc = exc.__cause__ or exc.__context__
  return None


def check_jax_backend() -> None:
  """Starts JAX's backend, so that a tool refuses an unusable `JAX_PLATFORMS` before it writes
  anything.

  Raises:
    UsageError: JAX cannot start the requested platform (`jax_backend_error`).
  """
  import jax

  try:
    jax.devices()
  except RuntimeError as e:
    message = jax_backend_error(e)
    if message is None:
      raise
    raise UsageError(message) from None


def describe_resource_error(e: OSError) -> str:
  """'disk full writing PATH (No space left on device)' and the like."""
  what = {
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
  }.get(e.errno, "permission denied")
  where = f" writing {e.filename}" if e.filename else ""
  return f"{what}{where} ({e.strerror or os.strerror(e.errno)}); nothing half-written was kept"


def fail(message: str, code: int = EXIT_USER) -> NoReturn:
  """Prints `error: message` on stderr and exits with `code`."""
  sys.stdout.flush()
  print(f"error: {message}", file=sys.stderr, flush=True)
  sys.exit(code)


def _clean(text: str) -> str:
  """One line: ml_collections puts a config file's formatted traceback into its message; keep
  the part before it and the traceback's last line (the exception)."""
  text = text.strip()
  if "Traceback (most recent call last)" in text:
    head = text.split(": Error whilst", 1)[0] if "Error whilst" in text else ""
    last = [line for line in text.splitlines() if line.strip()][-1].strip()
    text = f"{head}: {last}" if head else last
  return " ".join(text.split())


def _root_message(exc: BaseException) -> str:
  """The message of the innermost exception of `exc`'s chain (ml_collections wraps a config
  file's own error in an OSError saying that loading failed)."""
  seen, root = set(), exc
  while exc is not None and id(exc) not in seen:
    seen.add(id(exc))
    root = exc
    exc = exc.__cause__ or exc.__context__
  text = _clean(str(root))
  if isinstance(root, KeyError):
    text = text.strip("\"'")
  return text or type(root).__name__


def _flag_value(argv: Sequence[str], name: str) -> str | None:
  for i, a in enumerate(argv):
    if a.startswith(f"--{name}="):
      return a.split("=", 1)[1]
    if a == f"--{name}" and i + 1 < len(argv):
      return argv[i + 1]
  return None


def describe_flag_error(exc: BaseException, argv: Sequence[str]) -> str:
  """One message for a failure while parsing the command line: a bad flag value, a missing
  or failing config file, an unknown `--config.` field."""
  if isinstance(exc, flags.Error):
    text = _clean(str(exc)).removeprefix("ERROR:: ")  # absl's --flagfile errors
    if text.startswith("flag --"):
      return text.replace("flag --", "--", 1)
    named = _override_named_by(text, argv)
    return f"{named}: {text}" if named else text
  # ml_collections: a config file that cannot be loaded fails on first use of the flag's value.
  for name in ("config",):
    path = _flag_value(argv, name)
    if path is not None and ("Failed loading config file" in str(exc) or "config file" in str(exc)):
      file = path.split(":", 1)[0]
      if not os.path.exists(file):
        return f"--{name}={path}: config file {file} does not exist"
      return f"--{name}={path}: {_root_message(exc)}"
  if isinstance(exc, (KeyError, AttributeError)):
    key = _root_message(exc).split(";")[0].strip("\"' ")
    overrides = [a for a in argv if a.startswith("--config.")]
    named = [a for a in overrides if key in a.split("=", 1)[0].split(".")[1:]]
    flag = named[0] if named else f"--config...{key}"
    field = flag.split("=", 1)[0][len("--config.") :]
    hint = _root_message(exc).split(";", 1)[1].strip() if ";" in _root_message(exc) else ""
    return f"{flag}: the config has no field {field!r} ({key!r} is unknown)" + (
      f"; {hint}" if hint else ""
    )
  message = _root_message(exc)
  named = _override_named_by(message, argv) if isinstance(exc, (ValueError, TypeError)) else None
  return f"{named}: {message}" if named else message


def _override_named_by(message: str, argv: Sequence[str]) -> str | None:
  """The `--config.FIELD=VALUE` argument a parse failure's message is about (its value appears
  in the message, or it is the only override), or None."""
  overrides = [a for a in argv if a.startswith("--config.") and "=" in a]
  named = [a for a in overrides if a.split("=", 1)[1] and a.split("=", 1)[1] in message]
  if len(named) == 1:
    return named[0]
  return overrides[0] if len(overrides) == 1 else None


def parse_flags(argv: list[str]) -> list[str]:
  """absl's flag parsing, with `--help` exiting 0 and any parsing failure exiting 2 with one
  `error:` line (absl exits 1 for both)."""
  if any(a in _HELP for a in argv[1:]):
    flags.FLAGS.mark_as_parsed()
    app.usage(shorthelp="--helpfull" not in argv, writeto_stdout=True, exitcode=0)
  try:
    rest = flags.FLAGS(argv)
    for name in _CONFIG_FLAGS:
      if name in flags.FLAGS:
        # ml_collections keeps a config file's failure in a placeholder that raises on use.
        getattr(flags.FLAGS[name].value, "keys", None)
    return rest
  except Exception as e:  # every parsing failure is the command line's
    fail(describe_flag_error(e, argv))


def _main_with_exit_codes(main: Callable[[list[str]], Any]) -> Callable[[list[str]], Any]:
  def wrapped(argv: list[str]) -> int:
    return _handled(lambda: main(argv))

  return wrapped


# A tool's flags: `define(flag_values, argv)` defines them (argv lets a tool define flags that
# depend on others, e.g. prepare's `--config.` fields of the chosen `--source`), and
# `body(flag_values)` runs the tool and returns its exit status (None: 0).
Define = Callable[[flags.FlagValues, Sequence[str]], None]
Body = Callable[[flags.FlagValues], "int | None"]


def _handled(body: Callable[[], Any]) -> int:
  """Runs `body`, mapping user errors to `error:` + 2 and non-finite stops to 3."""
  try:
    code = body()
  except SystemExit as e:
    if e.code is None or isinstance(e.code, int):
      return int(e.code or 0)
    print(e.code, file=sys.stderr, flush=True)
    return EXIT_USER
  except FloatingPointError as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    return EXIT_NON_FINITE
  except _user_error_types() as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    return EXIT_USER
  except Exception as e:
    res = resource_error(e)
    message = describe_resource_error(res) if res else jax_backend_error(e) or path_error(e)
    if message is None:
      raise
    print(f"error: {message}", file=sys.stderr, flush=True)
    return EXIT_USER
  return int(code or 0)


def call(define: Define, body: Body, argv: Sequence[str], *, prog: str = "camrep") -> int:
  """Runs a tool in this process on `argv` (flags only, no program name) with its own
  `FlagValues`, as `python -m` would: returns the exit status and prints the `error:` line
  (for tests and notebooks; `--help` is for the command line)."""
  argv = [prog, *argv]
  fv = flags.FlagValues()

  def parse_and_run():
    try:
      define(fv, argv)  # a config dict's `--config.` overrides are parsed here already
      rest = fv(argv)
    except Exception as e:  # every parsing failure is the command line's
      raise UsageError(describe_flag_error(e, argv)) from None
    if len(rest) > 1:
      raise UsageError(f"unexpected arguments: {rest[1:]}")
    return body(fv)

  return _handled(parse_and_run)


def main(define: Define, body: Body) -> None:
  """A tool's `if __name__ == "__main__":` entry: its flags on absl's global FLAGS, absl's
  `--help`, and this module's exit codes."""
  try:
    define(flags.FLAGS, sys.argv)  # a config dict's `--config.` overrides are parsed here already
  except Exception as e:  # every parsing failure is the command line's
    if any(a in _HELP for a in sys.argv[1:]):
      raise
    fail(describe_flag_error(e, sys.argv))

  def main_(argv: list[str]) -> int | None:
    if len(argv) > 1:
      raise UsageError(f"unexpected arguments: {argv[1:]}")
    if not flags.FLAGS["verbosity"].present:  # jax and orbax log at INFO; -v 0 brings it back
      logging.set_verbosity(logging.WARNING)
    return body(flags.FLAGS)

  run(main_)


def run(main: Callable[[list[str]], Any], argv: list[str] | None = None) -> None:
  """`absl.app.run(main)` with this module's flag parsing and exit codes."""
  app.run(_main_with_exit_codes(main), argv=argv, flags_parser=parse_flags)


def overridden(flag_values: flags.FlagValues | None = None, name: str = "config") -> set[str]:
  """The config fields set on the command line (`--config.a.b=...` -> "a.b")."""
  fv = flags.FLAGS if flag_values is None else flag_values
  prefix = f"{name}."
  return {k[len(prefix) :] for k in fv if k.startswith(prefix) and fv[k].present}


def peek_flag(argv: Sequence[str], name: str, default: str | None = None) -> str | None:
  """The value of `--name=V` / `--name V` in argv before parsing (for flags that decide which
  other flags exist), else `default`."""
  value = _flag_value(argv, name)
  return default if value is None else value


def _override_default(value: Any) -> Any:
  """A `--config.` field's default: scalars keep their type (parsed as such); tuples, mappings
  and None become untyped placeholders that take a Python literal."""
  from ml_collections import config_dict

  if isinstance(value, (bool, int, float, str)):
    return value
  return config_dict.placeholder(object)


def define_overrides(
  fv: flags.FlagValues, argv: Sequence[str], defaults: Mapping[str, Any], help_string: str
) -> None:
  """Defines `--config.FIELD=VALUE` flags over `defaults` (a constructor's keyword arguments):
  an unknown field is an error, scalar values are parsed as their default's type, others
  (tuples, mappings, None defaults) as Python literals (`--config.scenes="('chess',)"`)."""
  from ml_collections import config_dict, config_flags

  config = config_dict.ConfigDict({k: _override_default(v) for k, v in defaults.items()})
  config_flags.DEFINE_config_dict(
    "config", config, help_string, flag_values=fv, lock_config=True, sys_argv=list(argv)
  )
  # A key flag of the tool that asked for it, so that its `--help` lists it (absl lists the main
  # module's key flags; ml_collections gives the flag to this module).
  caller = sys._getframe(1).f_globals.get("__name__", "")
  fv.register_key_flag_for_module(sys.argv[0] if caller == "__main__" else caller, fv["config"])


def overrides(fv: flags.FlagValues) -> dict[str, Any]:
  """{field: value} of the `--config.` fields set on the command line (`define_overrides`)."""
  if "config" not in fv:
    return {}
  config = fv["config"].value
  return {k: config[k] for k in sorted(overridden(fv)) if "." not in k}
