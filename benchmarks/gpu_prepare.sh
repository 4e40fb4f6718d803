#!/usr/bin/env bash
# Prepare, here, the splax peer for benchmarks/gpu_check.py on a GPU machine that has no package registry:
#   bash benchmarks/gpu_prepare.sh SPLAX_GIT_DIR      # a clone (or bare mirror) of github.com/chungmin99/splax
# writes .peers/splax/src (splax's source) and .peers/wheels/ (jaxlie and what it needs that such an image
# lacks, pure-Python wheels); both folders are git-ignored (.git/info/exclude). Carry .peers to the machine and run
#   python3 -m pip install -q --no-index --no-deps --target /tmp/peers .peers/wheels/*.whl
#   PYTHONPATH=/tmp/peers:$PYTHONPATH python3 benchmarks/gpu_check.py --splax-src .peers/splax/src ...
set -euo pipefail
SPLAX=${1:?usage: bash benchmarks/gpu_prepare.sh SPLAX_GIT_DIR}
grep -qx "/.peers/" .git/info/exclude 2>/dev/null || echo "/.peers/" >> .git/info/exclude
rm -rf .peers/splax && mkdir -p .peers/splax .peers/wheels
# (a mirror without splax's large example GIFs prints "invalid object" for them: only src/ is taken)
git -C "$SPLAX" archive HEAD -- src | tar -x -C .peers/splax
git -C "$SPLAX" log -1 --format='splax %H %cd' > .peers/splax/REVISION
python3 -m pip download -q --no-deps --only-binary=:all: -d .peers/wheels \
  jaxlie==1.5.0 jax_dataclasses==1.6.3 tyro==1.0.17 docstring_parser==0.18.0 shtab==1.13.0 typeguard==4.6.1
du -sh .peers
