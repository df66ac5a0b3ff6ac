#!/usr/bin/env bash
# Submits a sharded relight bake to Slurm: an array of SHARDS bake tasks and
# a merge that starts when all of them have succeeded.
#
#   SCENE=/data/sponza/scene.toml TECHNIQUE=prm SHARDS=4 OUT=/data/bakes/sponza \
#     BAKE_ARGS="--set clusters=256" bash submit.sh
#
# Resubmitting after a failed task bakes only the shards that are missing.
set -euo pipefail
: "${SCENE:?}" "${TECHNIQUE:?}" "${SHARDS:?}" "${OUT:?}"
here=$(cd "$(dirname "$0")" && pwd)
export SCENE TECHNIQUE SHARDS OUT BAKE_ARGS="${BAKE_ARGS:-}" RELIGHT="${RELIGHT:-relight}"
array=$(sbatch --parsable --export=ALL --array="0-$((SHARDS - 1))" "$here/bake-shard.sbatch")
merge=$(sbatch --parsable --export=ALL --dependency="afterok:${array%%;*}" "$here/merge.sbatch")
echo "bake array $array, merge $merge: the bake will be $OUT/${BAKE_NAME:-scene.bake}"
