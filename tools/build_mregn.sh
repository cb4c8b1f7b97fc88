#!/usr/bin/env bash
# Builds the authors' C tools (mregn: mre-learn, gn-learn, mregn-generate, mregn-lyapunov; its rnn/
# subfolder: rnn-learn, rnn-generate, rnn-lyapunov) from a checkout YOU name, with the source lists
# and defines of their Makefile.am files (gcc -O2 -fopenmp, -DENABLE_ADAPTIVE_LEARNING_RATE
# -DENABLE_ATTRACTION_OF_INIT_C), without autotools. Their code is never copied into moex.
#
#   bash tools/build_mregn.sh <mregn checkout> <bin folder> [extra CFLAGS, e.g. -DMIN_VARIANCE=0.0025]
#
# Get the checkout with: git clone https://github.com/jnamika/mregn (commit 6a92a19 was used).
set -euo pipefail
if [ $# -lt 2 ]; then
    echo "usage: bash tools/build_mregn.sh <mregn checkout> <bin folder> [CFLAGS ...]" >&2; exit 2
fi
src=$(cd "$1" 2>/dev/null && pwd) || { echo "no folder $1" >&2; exit 2; }
[ -f "$src/src/common/mre.c" ] && [ -f "$src/rnn/src/common/rnn.c" ] \
    || { echo "$1 is not an mregn checkout (no src/common/mre.c, rnn/src/common/rnn.c)" >&2; exit 2; }
mkdir -p "$2"; out=$(cd "$2" && pwd); shift 2
inc=$(mktemp -d); trap 'rm -rf "$inc"' EXIT
: > "$inc/config.h"  # autoconf's header: nothing the tools read but ENABLE_MTRACE (left off)
R=$src/rnn/src; M=$src/src
defs="-DENABLE_ADAPTIVE_LEARNING_RATE -DENABLE_ATTRACTION_OF_INIT_C -D_POSIX_C_SOURCE=200112L"
build() {  # name, include folders, sources...
    local name=$1 incs=$2; shift 2
    # shellcheck disable=SC2086
    gcc -std=gnu99 -O2 -fopenmp -I "$inc" $incs $defs "$@" -o "$out/$name" ${EXTRA_CFLAGS:-} -lm
    echo "built $out/$name"
}
EXTRA_CFLAGS="$*"
build mre-learn "-I $M/common -I $R/common -I $R/rnn-learn" $M/mre-learn/{main,training,print}.c \
    $M/common/mre.c $R/common/{rnn,utils}.c $R/rnn-learn/{parse,target}.c
build gn-learn "-I $M/common -I $R/common -I $R/rnn-learn" $M/gn-learn/{main,training,print}.c \
    $M/common/{mre,mregn,mregn_lyapunov}.c $R/common/{rnn,entropy,solver,utils}.c $R/rnn-learn/parse.c
build mregn-generate "-I $M/common -I $R/common" $M/mregn-generate/main.c \
    $M/common/{mre,mregn_runner}.c $R/common/{rnn,utils}.c
build mregn-lyapunov "-I $M/common -I $R/common" $M/mregn-lyapunov/{main,lyapunov}.c \
    $M/common/{mre,mregn_runner,mregn_lyapunov}.c $R/common/{rnn,solver,utils}.c
build rnn-learn "-I $R/common" $R/rnn-learn/{main,target,training,print,parse}.c \
    $R/common/{rnn,rnn_lyapunov,entropy,solver,utils}.c
build rnn-generate "-I $R/common" $R/rnn-generate/main.c $R/common/{rnn,rnn_runner,utils}.c
build rnn-lyapunov "-I $R/common" $R/rnn-lyapunov/{main,lyapunov}.c \
    $R/common/{rnn,rnn_runner,rnn_lyapunov,solver,utils}.c
