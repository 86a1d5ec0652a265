# Source from the repository's root (`. scripts/activate.sh`): puts .venv/ first on PATH where scripts/install.sh
# installed there (an externally managed system Python); changes nothing where it installed into the Python it ran.
if [ -f .venv/bin/activate ]; then
  . .venv/bin/activate
fi
