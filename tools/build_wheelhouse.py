"""Build the wheelhouse a GPU machine needs to run camrep: the project's dependencies it lacks.

The GPU machines (nvidia-h100-x1, nvidia-h200; /work/.library/device/KINDS.md) run Python
3.12 on x86-64 with JAX, Flax, Optax, Orbax, chex, OpenCV and a long list of other packages
(`GPU_IMAGE`), and reach no package registry. This script, run on the CPU machine:

  1. reads camrep's dependencies from pyproject.toml ([project] dependencies);
  2. walks their requirements through the packages installed in this interpreter's environment
     (importlib.metadata; markers evaluated for the GPU's Python 3.12 on Linux x86-64), pinning
     each to the version installed here (the project's stack, e.g. /work/main/.venv);
  3. drops what the GPU image already has (and does not walk into it: the image has its
     requirements), except protobuf (`ALWAYS_CARRY`: tfds' generated code needs the runtime it
     was tested with);
  4. downloads the rest as wheels for CPython 3.12 manylinux x86-64 (`pip download --no-deps
     --only-binary=:all:`), or builds a wheel where the index has only a source archive (`pip
     wheel --no-deps`, pure-Python packages), into `--out` (default `.whl/`, git-ignored).

Commands (repository root):

  .venv/bin/python tools/build_wheelhouse.py --list    # what it would fetch, no download
  .venv/bin/python tools/build_wheelhouse.py           # -> .whl/ (a few MB, ~1 min)

On the GPU machine (the device tool's `run` with carry=[".whl"]), before camrep is imported:

  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD

`python -m camrep.bench.gpu_report --dry_run` prints both, with the report's commands.
"""

from __future__ import annotations

import argparse
import importlib.metadata as md
import os
import re
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Iterable

from packaging.markers import default_environment
from packaging.requirements import Requirement

from camrep.bench import gpu_report

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The GPU image's Python packages ("cuda" image, KINDS.md "Python packages already there", read
# on 2026-11-17). Carried wheels would only shadow these with other versions.
GPU_IMAGE = frozenset(
  """absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs
  botorch build certifi charset-normalizer chex click cloudpickle cmake colorama contourpy
  coverage cuda-bindings cuda-core cuda-pathfinder cuda-toolkit cupy-cuda13x cycler cython diffrax
  e3nn einops equinox etils execnet filelock flatbuffers flax fonttools formulaic frozenlist fsspec
  gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna imageio
  iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib
  kiwisolver lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml
  markdown markdown-it-py markupsafe matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack
  multidict multipledispatch mypy-extensions nanobind narwhals networkx ninja numba numba-cuda
  numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
  nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse
  nvidia-cusparselt-cu13 nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13
  nvidia-nvtx onnx onnx-ir onnxruntime onnxscript opencv-python-headless optax opt-einsum
  opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy peft pillow pip pluggy
  portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
  pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock
  pytest-timeout pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich
  sacrebleu safetensors scikit-build-core scikit-image scikit-learn scipy seaborn sentencepiece
  sentence-transformers setuptools shellingham simplejson six sortedcontainers statsmodels sympy
  tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
  tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm
  transformers treescope triton typer typing-extensions typing-inspect urllib3 uvloop
  wadler-lindig werkzeug wheel wrapt xarray xxhash yarl zipp""".split()
)

# Carried even though the image has them: the generated code of tensorflow-metadata and tfds
# (and grain's protos) must run on the protobuf runtime they were tested with here.
ALWAYS_CARRY = frozenset({"protobuf"})

# The GPU machine's interpreter and platform (KINDS.md: Python 3.12.3, x86-64 Linux).
TARGET_PYTHON = "3.12"
TARGET_ENV = {
  "python_version": TARGET_PYTHON,
  "python_full_version": "3.12.3",
  "implementation_name": "cpython",
  "platform_python_implementation": "CPython",
  "sys_platform": "linux",
  "platform_system": "Linux",
  "os_name": "posix",
  "platform_machine": "x86_64",
}
PLATFORMS = (
  "manylinux_2_28_x86_64",
  "manylinux_2_27_x86_64",
  "manylinux_2_24_x86_64",
  "manylinux_2_17_x86_64",
  "manylinux2014_x86_64",
  "manylinux1_x86_64",
)


def canonical(name: str) -> str:
  """PEP 503 normalised project name ("Tensorflow_Datasets" -> "tensorflow-datasets")."""
  return re.sub(r"[-_.]+", "-", name).lower()


def project_dependencies(pyproject: str) -> list[str]:
  """The [project] dependencies of a pyproject.toml, as requirement strings."""
  with open(pyproject, "rb") as f:
    return list(tomllib.load(f)["project"]["dependencies"])


def _applies(req: Requirement, env: dict[str, str]) -> bool:
  """Whether a requirement applies on the target without extras."""
  return req.marker is None or req.marker.evaluate({**env, "extra": ""})


def closure(
  requirements: Iterable[str],
  *,
  exclude: frozenset[str] = GPU_IMAGE - ALWAYS_CARRY,
  version_of=None,
  requires_of=None,
) -> tuple[dict[str, str], list[str]]:
  """Packages to carry: the requirements and, recursively, theirs, less `exclude`.

  Args:
    requirements: requirement strings (PEP 508).
    exclude: canonical names already on the target; not carried, not walked into.
    version_of: name -> installed version or None (default: importlib.metadata here).
    requires_of: name -> list of requirement strings (default: importlib.metadata here).

  Returns:
    ({canonical name: pinned version}, [names required but not installed here]).
  """
  version_of = version_of or _installed_version
  requires_of = requires_of or (lambda n: md.distribution(n).requires or [])
  env = {**default_environment(), **TARGET_ENV}
  pinned: dict[str, str] = {}
  missing: list[str] = []
  todo = [Requirement(r) for r in requirements]
  while todo:
    req = todo.pop()
    name = canonical(req.name)
    if not _applies(req, env) or name in exclude or name in pinned or name in missing:
      continue
    version = version_of(name)
    if version is None:
      missing.append(name)
      continue
    pinned[name] = version
    todo += [Requirement(r) for r in requires_of(name)]
  return dict(sorted(pinned.items())), sorted(missing)


def _installed_version(name: str) -> str | None:
  try:
    return md.version(name)
  except md.PackageNotFoundError:
    return None


def download_command(name: str, version: str, out: str) -> list[str]:
  """`pip download` of one pinned wheel for the GPU's Python and platform, no dependencies."""
  cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
  cmd += ["--python-version", TARGET_PYTHON, "--implementation", "cp"]
  for p in PLATFORMS:
    cmd += ["--platform", p]
  return [*cmd, "-d", out, f"{name}=={version}"]


def wheel_command(name: str, version: str, out: str) -> list[str]:
  """`pip wheel` of one pinned source archive (pure-Python packages with no wheel on the index)."""
  return [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", out, f"{name}=={version}"]


def install_command(wheelhouse: str = ".whl") -> str:
  """The GPU machine's command that installs the carried wheels (the GPU report's own)."""
  return gpu_report.install_command(wheelhouse)


def ensure_ignored(out: str) -> None:
  """Makes sure git ignores the wheelhouse (.gitignore has /.whl/; other folders go to
  .git/info/exclude), so the wheels travel only where `carry` names them."""
  rel = os.path.relpath(os.path.abspath(out), ROOT)
  if rel.startswith("..") or rel == ".whl":
    return
  exclude = os.path.join(ROOT, ".git", "info", "exclude")
  if os.path.isdir(os.path.dirname(exclude)):
    lines = open(exclude).read().splitlines() if os.path.exists(exclude) else []
    if f"/{rel}/" not in lines:
      with open(exclude, "a") as f:
        f.write(f"/{rel}/\n")


def build(pinned: dict[str, str], out: str) -> list[str]:
  """Fetches every pinned wheel into `out`; returns the names that failed."""
  os.makedirs(out, exist_ok=True)
  failed = []
  for name, version in pinned.items():
    print(f"  {name}=={version}", flush=True)
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    ok = subprocess.call(download_command(name, version, out), **quiet) == 0
    if not ok:
      print("    no wheel for the target on the index; building one from source", flush=True)
      ok = subprocess.call(wheel_command(name, version, out), **quiet) == 0
    if not ok:
      failed.append(name)
  return failed


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--out", default=os.path.join(ROOT, ".whl"), help="wheelhouse folder")
  p.add_argument("--list", action="store_true", help="print what would be fetched; download none")
  p.add_argument("--pyproject", default=os.path.join(ROOT, "pyproject.toml"))
  p.add_argument("--clean", action="store_true", help="empty --out first")
  args = p.parse_args(argv)
  pinned, missing = closure(project_dependencies(args.pyproject))
  print(
    f"camrep's dependencies to carry (missing from the GPU image, and protobuf), pinned to this "
    f"environment "
    f"({sys.executable}, Python {sys.version.split()[0]}): {len(pinned)}"
  )
  for name, version in pinned.items():
    print(f"  {name}=={version}")
  if missing:
    print(f"required for Python {TARGET_PYTHON} but not installed here (not carried): {missing}")
  if args.list:
    print(f"install on the GPU machine (carry {os.path.relpath(args.out, ROOT)}):")
    print(f"  {install_command(os.path.relpath(args.out, ROOT))}")
    return 0
  if args.clean and os.path.isdir(args.out):
    shutil.rmtree(args.out)
  ensure_ignored(args.out)
  failed = build(pinned, args.out)
  wheels = sorted(f for f in os.listdir(args.out) if f.endswith(".whl"))
  size = sum(os.path.getsize(os.path.join(args.out, f)) for f in wheels) / 2**20
  print(f"{len(wheels)} wheels, {size:.1f} MiB in {args.out}")
  if failed:
    print(f"FAILED: {failed}")
    return 1
  if size > 60:
    print("warning: the device tool carries at most 64 MiB with the working tree")
  return 0


if __name__ == "__main__":
  sys.exit(main())
