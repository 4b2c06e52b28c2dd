#!/bin/sh
# Create .venv/ at the repository root and install jaxbody (editable) with its `test` extra.
#
# Idempotent: skipped when .venv/ holds a finished install for the current pyproject.toml
# (its SHA-256 is kept in .venv/.jaxbody-bootstrap). Needs Python >= 3.11 as `python3.11`,
# or as `python3`; set JAXBODY_PYTHON=/path/to/python to choose another interpreter.
set -eu

root=$(CDPATH= cd -- "$(dirname -- "$0")/.." && pwd)
cd "$root"
venv="$root/.venv"
stamp="$venv/.jaxbody-bootstrap"

if [ -z "${JAXBODY_PYTHON:-}" ]; then
  if command -v python3.11 >/dev/null 2>&1 && python3.11 -c '' >/dev/null 2>&1; then
    JAXBODY_PYTHON=python3.11
  elif command -v python3 >/dev/null 2>&1; then
    JAXBODY_PYTHON=python3
  else
    echo "bootstrap: no python3.11 or python3 on PATH; install Python >= 3.11" >&2
    exit 1
  fi
fi

hash_pyproject() {
  "$1" -c 'import hashlib, sys; print(hashlib.sha256(open("pyproject.toml", "rb").read()).hexdigest())'
}

if [ -x "$venv/bin/python" ] && [ -x "$venv/bin/jaxbody" ] && [ -f "$stamp" ] \
  && [ "$(cat "$stamp")" = "$(hash_pyproject "$venv/bin/python")" ]; then
  exit 0
fi

if ! "$JAXBODY_PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "bootstrap: jaxbody needs Python >= 3.11; $JAXBODY_PYTHON is $("$JAXBODY_PYTHON" --version 2>&1)" >&2
  exit 1
fi

echo "bootstrap: installing jaxbody[test] into $venv (takes a minute or two the first time)" >&2
if [ ! -x "$venv/bin/python" ]; then
  "$JAXBODY_PYTHON" -m venv "$venv"
fi
rm -f "$stamp"
"$venv/bin/python" -m pip install --quiet --upgrade pip
"$venv/bin/python" -m pip install --quiet -e ".[test]"
hash_pyproject "$venv/bin/python" > "$stamp"
echo "bootstrap: done" >&2
