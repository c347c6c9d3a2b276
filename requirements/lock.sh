#!/usr/bin/env bash
# Regenerates requirements/constraints.txt, the pinned stack that the README's set-up command and
# .ci/run install: the newest versions PYTHON's pip resolves for camrep[dev] today, in a throwaway
# virtual environment. Run from anywhere, then run the tests and commit the file:
#   requirements/lock.sh [PYTHON]        # default: python3
set -euo pipefail
cd "$(dirname "$0")/.."
python=${1:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$python" -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install -q --upgrade pip
"$tmp/venv/bin/pip" install -q '.[dev]'
version=$("$tmp/venv/bin/python" -c 'import platform; print(platform.python_version(), platform.system(), platform.machine())')
{
  echo "# camrep[dev]'s pinned stack, resolved by requirements/lock.sh on Python $version."
  echo "# Install: pip install -e '.[dev]' -c requirements/constraints.txt (README, .ci/run)."
  "$tmp/venv/bin/pip" freeze --exclude camrep
} > requirements/constraints.txt
echo "wrote requirements/constraints.txt ($(grep -vc '^#' requirements/constraints.txt) packages)"
