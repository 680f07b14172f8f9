# Sourced by the two entry scripts: create (once) a virtual environment and install the project into it.
# usage: bootstrap_venv DIR EXTRAS
bootstrap_venv() {
  local venv="$1" extras="$2"
  local python="${SSP_REHAB_PYTHON:-python3.11}"
  command -v "$python" >/dev/null 2>&1 || python=python3
  if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
  fi
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -e ".${extras}"
}
