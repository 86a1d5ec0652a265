#!/usr/bin/env bash
# Prepares, on a machine with a package index, what benchmarks/gpu_run.sh needs on a GPU machine that has none and
# takes at most 64 MiB of files per call (the working tree, some 12 MB, included):
#   .carry/c01 ... cNN  the wheels (warp-lang 1.19.0, open3d 0.20.0 with CUDA, pyrender 0.1.45 and what they import)
#                       for Python 3.12, joined and cut into 48 MB chunks; the last holds install.py, which cuts the
#                       wheels back out by their sizes and installs them into /tmp/site
#   .gl/*.deb           libEGL and its kin (glvnd; open3d's CUDA build loads libEGL.so.1, pyrender draws through EGL):
#                       unpacked there with `dpkg -x DEB /`, no apt
#   .carry/data         the shared data's first FRAMES (default 50) frames of TUM fr1_rpy, the bunny's mesh and
#                       Kenney's desk chair
#   .carry/pytest       pytest's wheels (gpu_run.sh's gbcheck step runs tests there; carry it with the data)
#   .olds/photoreg      the package at commit OLD (default HEAD) for gpu_run.sh's A/B steps (OLD=/tmp/olds there)
# The folders are kept out of git (.git/info/exclude). Then, one call per chunk, back to back (the machine goes back
# some 30 s after a call, its /tmp with it):
#   run(carry=[".carry/c01"], command="mkdir -p /tmp/chunks && cp .carry/c01/* /tmp/chunks/")
#   run(carry=[".carry/cNN"], command="cp .carry/cNN/* /tmp/chunks/")                      (c02 ... the one before last)
#   run(carry=[".carry/cLAST"], command="cp .carry/cLAST/* /tmp/chunks/ && python3 /tmp/chunks/install.py")
#   run(carry=[".carry/data", ".carry/pytest", ".gl", ".olds"], command="mkdir -p /tmp/data && cp -r .carry/data/* /tmp/data/ &&
#       for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig; cp -r .olds /tmp/olds;
#       PHOTOREG_DATA=/tmp/data OLD=/tmp/olds bash benchmarks/gpu_run.sh /tmp/data/recordings/tum_fr1_rpy $OUT STEP...")
# usage (from the repository root): bash benchmarks/gpu_carry.sh   (PHOTOREG_DATA must name the shared data)
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
: "${PHOTOREG_DATA:?PHOTOREG_DATA must name the shared data folder}"
frames=${FRAMES:-50}
old=${OLD:-HEAD}
for d in /.carry/ /.gl/ /.olds/; do grep -qx "$d" .git/info/exclude 2>/dev/null || echo "$d" >> .git/info/exclude; done

rm -rf .carry .gl .olds
mkdir -p .carry/wheels .gl .olds
echo "wheels for Python 3.12 ..."
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .carry/wheels \
  warp-lang==1.19.0 open3d==0.20.0 pyrender==0.1.45 trimesh==4.5.3 PyOpenGL==3.1.10 freetype-py imageio networkx \
  addict configargparse OpenEXR
( cd .carry && cat wheels/*.whl > all.bin && split -b 48000000 -d -a 2 all.bin part && rm all.bin )
n=0
for p in .carry/part*; do n=$((n + 1)); d=$(printf '.carry/c%02d' $n); mkdir -p "$d"; mv "$p" "$d/"; done
python3 - "$(printf '.carry/c%02d' $n)" <<'PY'
import os, sys
names = sorted(os.listdir(".carry/wheels"))
sizes = [os.path.getsize(".carry/wheels/" + n) for n in names]
open(sys.argv[1] + "/install.py", "w").write(f'''"""Joins the chunks in /tmp/chunks, cuts the wheels out by their sizes, installs them into /tmp/site."""
import glob, os, subprocess, sys
os.chdir("/tmp/chunks")
data = b"".join(open(p, "rb").read() for p in sorted(glob.glob("part*")))
assert len(data) == {sum(sizes)}, ("chunks missing", len(data))
off = 0
for name, size in zip({names!r}, {sizes!r}):
    open(name, "wb").write(data[off:off + size])
    off += size
del data
subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--target",
                "/tmp/site", *{names!r}], check=True)
for f in glob.glob("part*") + glob.glob("*.whl"):
    os.remove(f)
print("installed into /tmp/site:", len(glob.glob("/tmp/site/*.dist-info")), "packages")
''')
PY
rm -rf .carry/wheels
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp --platform any \
  -d .carry/pytest pytest pluggy iniconfig packaging
echo "EGL packages ..."
( cd .gl && apt-get download libegl1 libglvnd0 libgl1 libglx0 libopengl0 libgles2 libegl-mesa0 libgbm1 libglapi-mesa \
    libwayland-client0 libwayland-server0 libxcb-randr0 libx11-xcb1 libxcb-dri3-0 libxcb-present0 libxcb-sync1 \
    libxshmfence1 libxcb-xfixes0 libdrm2 libusb-1.0-0 2>&1 | grep -v "^W: " | tail -1 )
echo "data: TUM fr1_rpy's first $frames frames, the bunny ..."
src=$PHOTOREG_DATA/recordings/tum_fr1_rpy
dst=.carry/data/recordings/tum_fr1_rpy
mkdir -p "$dst/rgb" "$dst/depth" .carry/data/meshes
head -n "$frames" "$src/associations.txt" > "$dst/associations.txt"
cp "$src"/{rgb,depth,groundtruth,intrinsics,accelerometer}.txt "$dst/"
awk '{print $2; print $4}' "$dst/associations.txt" | while read -r f; do cp "$src/$f" "$dst/$f"; done
cp "$PHOTOREG_DATA/meshes/bunny_5k.obj" .carry/data/meshes/
mkdir -p .carry/data/meshes/kenney_chairs   # the several materials' G-buffer test (gpu_run.sh gbcheck)
cp "$PHOTOREG_DATA/meshes/kenney_chairs/chairDesk.glb" .carry/data/meshes/kenney_chairs/
git archive "$old" photoreg | tar -x -C .olds
du -sh .carry/c* .carry/data .gl .olds | tr '\n' ' '; echo
