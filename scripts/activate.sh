# Source from the repository's root (`. scripts/activate.sh`): puts .venv/ first on PATH where scripts/install.sh
# installed there last (an externally managed system Python: .venv/photoreg-installed); changes nothing where it
# installed into the Python it ran with.
if [ -f .venv/photoreg-installed ]; then
  . .venv/bin/activate
fi
