#!/usr/bin/env bash
# Build the reference collision checker, vamp-planner (the Kavraki lab's VAMP),
# from PyPI's source package without reaching GitHub, into its own venv.
#
# VAMP is only a reference for benchmarks/bench_limit.py: it is not a dependency
# of gcm_pipeline and is never installed into the project's venv.
#
# Its CMake build downloads CPM.cmake (a release asset) and, through CPM,
# nanobind, nigh, pdqsort and SIMDxorshift from GitHub.  This script takes
# local snapshots of those repositories instead (it does not fetch them itself):
#
#   SNAP/nanobind      wjakob/nanobind      at 9a25aed8a7edfe60ef9ad1c911e57667bc4916c4,
#                      with ext/robin_map = Tessil/robin-map at 4ec1bf19c6a96125ea22062f38c2cf5b958e448e
#   SNAP/nigh          KavrakiLab/nigh      at 97130999440647c204e0265d05a997dbd8da4e70 (only src/ is used)
#   SNAP/pdqsort       orlp/pdqsort         at b1ef26a55cdb60d236a5cb199c4234c704f46726
#   SNAP/SIMDxorshift  lemire/SIMDxorshift  at 857c1a01df53cf1ee1ae8db3238f0ef42ef8e490
#   SNAP/CPM.cmake     cpm-cmake/CPM.cmake  at tag v0.40.1
#
# (these are the commits vamp-planner 0.6.4's cmake/Dependencies.cmake,
# cmake/Python.cmake and cmake/FetchInitCPM.cmake name).  From a git clone or
# mirror of each repository, export a work tree with e.g.
#   git --git-dir=<mirror> archive <commit> | tar -x -C SNAP/<name>
# (for nigh, `-- . ':(exclude)test/fkmap100000.txt'` if that large test file is
# not in the mirror).  The CPM.cmake release asset is the repository's
# cmake/CPM.cmake with its version line set to 0.40.1; the script rebuilds it
# and checks the SHA-256 VAMP expects, then places it where VAMP's
# file(DOWNLOAD) finds it already present (CMake then skips the download).
#
# Result: VENV with the `vamp` package (robots sphere, ur5, panda by default)
# and VENV/bin/vamp_bench, the C++ harness of benchmarks/vamp/vamp_bench.cc.
#
# Usage:  benchmarks/vamp/build_vamp.sh SNAP [VENV] [WORK]
#   SNAP  directory holding the five snapshots above
#   VENV  venv to create/use (default /work/vampvenv)
#   WORK  scratch directory for the sdist and the build tree (default /work/vampbuild)
# Environment: VAMP_VERSION (default 0.6.4), VAMP_ROBOTS (default "sphere;ur5;panda";
#   VAMP's own default also builds fetch and baxter), CMAKE_BUILD_PARALLEL_LEVEL (default 1).
# Needs: python3 with venv and headers, g++, cmake >= 3.16, Eigen 3 headers
#   (Debian: apt-get install libeigen3-dev), PyPI for numpy, scikit-build-core and the sdist.
set -euo pipefail

SNAP=${1:?usage: build_vamp.sh SNAP [VENV] [WORK]}
VENV=${2:-/work/vampvenv}
WORK=${3:-/work/vampbuild}
VERSION=${VAMP_VERSION:-0.6.4}
ROBOTS=${VAMP_ROBOTS:-sphere;ur5;panda}
export CMAKE_BUILD_PARALLEL_LEVEL=${CMAKE_BUILD_PARALLEL_LEVEL:-1}
SNAP=$(realpath "$SNAP")

for d in nanobind/ext/robin_map/include nigh/src pdqsort SIMDxorshift/src CPM.cmake/cmake; do
    [ -d "$SNAP/$d" ] || { echo "build_vamp.sh: missing snapshot directory $SNAP/$d" >&2; exit 2; }
done
[ -d /usr/include/eigen3 ] || { echo "build_vamp.sh: Eigen 3 headers not found (apt-get install libeigen3-dev)" >&2; exit 2; }

mkdir -p "$WORK"
cd "$WORK"

# 1. The venv with what the build backend needs (no build isolation: pip would
#    otherwise try to install nanobind and cmake from PyPI into a temporary env;
#    the system cmake is used).
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/pip" install -q numpy scikit-build-core typing_extensions

# 2. The source package, unpacked (its build tree goes in WORK/build).
SDIST=vamp_planner-$VERSION.tar.gz
if [ ! -f "$SDIST" ]; then
    # Without build isolation, preparing the metadata needs only scikit-build-core
    # (with isolation pip would first install nanobind and cmake into a temporary env).
    "$VENV/bin/pip" download -q --no-deps --no-binary :all: --no-build-isolation \
        -d . "vamp-planner==$VERSION"
fi
rm -rf "vamp_planner-$VERSION"
tar xzf "$SDIST"
SRC=$WORK/vamp_planner-$VERSION
BUILD=$WORK/build

# 3. CPM.cmake 0.40.1 where FetchInitCPM.cmake downloads it to.
mkdir -p "$BUILD/cmake"
sed 's/set(CURRENT_CPM_VERSION 1.0.0-development-version)/set(CURRENT_CPM_VERSION 0.40.1)/' \
    "$SNAP/CPM.cmake/cmake/CPM.cmake" > "$BUILD/cmake/CPM.cmake"
echo "117cbf2711572f113bab262933eb5187b08cfc06dce0714a1ee94f2183ddc3ec  $BUILD/cmake/CPM.cmake" | sha256sum -c -

# 4. Build and install, every CPM package from its snapshot.
"$VENV/bin/pip" install -v --no-build-isolation --no-deps \
    -C build-dir="$BUILD" \
    -C cmake.define.CPM_nanobind_SOURCE="$SNAP/nanobind" \
    -C cmake.define.CPM_nigh_SOURCE="$SNAP/nigh" \
    -C cmake.define.CPM_pdqsort_SOURCE="$SNAP/pdqsort" \
    -C cmake.define.CPM_SIMDxorshift_SOURCE="$SNAP/SIMDxorshift" \
    -C "cmake.define.VAMP_ROBOT_MODULES=$ROBOTS" \
    -C "cmake.define.VAMP_ROBOT_STRUCTS=$(echo "$ROBOTS" | sed 's/sphere/Sphere/;s/ur5/UR5/;s/panda/Panda/;s/fetch/Fetch/;s/baxter/Baxter/')" \
    "$SRC" > "$WORK/build.log" 2>&1 || { tail -40 "$WORK/build.log" >&2; exit 1; }

# 5. Smoke test.
"$VENV/bin/python" -c "import vamp; print('vamp', vamp.robots)"

# 6. The C++ timing harness of bench_limit.py (VAMP's checker without the Python
#    binding in the loop), against the sdist's headers, with the flags of VAMP's
#    cmake/CompilerSettings.cmake for a Release build on x86_64 with GCC.
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
g++ -std=c++17 -O3 -march=native -mavx2 -fno-math-errno -fno-signed-zeros -fno-trapping-math \
    -fno-rounding-math -ffp-contract=fast -fassociative-math -Wno-ignored-attributes \
    -I "$SRC/src/impl" -I /usr/include/eigen3 -I "$SNAP/pdqsort" -I "$SNAP/nigh/src" \
    -I "$SNAP/SIMDxorshift/include" \
    "$HERE/vamp_bench.cc" -o "$VENV/bin/vamp_bench"
echo "built $VENV/bin/vamp_bench"
