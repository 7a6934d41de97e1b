#!/bin/bash
# Results tables of the non-learning agents (RESULTS.md): sun360_mini test splits (indoor, outdoor; FoV 90, 60)
# and the synthetic test split. Needs the datasets made first, e.g.
#   python tools/make_dataset.py dataset=sun360_indoor dataset.root=$MINI dataset.out_dir=data/sun360_mini_indoor dataset.name=sun360_mini_indoor dataset.episodes_per_image=10
# (and the same for outdoor). Then: python benchmarks/agent_tables.py outputs/bench
cd "$(dirname "$0")/.."
PY=${PY:-python}
MINI=${MINI:-${FINDVIEW_SUN360_MINI:?set FINDVIEW_SUN360_MINI (or MINI) to the folder of the sun360_mini panoramas}}
for sub in indoor outdoor; do
 for sim in fov90 fov60; do
  for agent in random oracle orb sift rotation; do
   out=outputs/bench/sun360_mini_${sub}_${sim}/${agent}; mkdir -p $(dirname $out)
   [ -f $out/summary.json ] && continue
   $PY tools/eval.py agent=$agent dataset=sun360_${sub} dataset.root=$MINI dataset.out_dir=data/sun360_mini_${sub} dataset.name=sun360_mini_${sub} sim=$sim split=test progress=false hydra.run.dir=$out > $out.log 2>&1 || echo FAIL $out
  done
 done
done
for agent in random oracle orb sift rotation; do
  out=outputs/bench/synthetic_fov90/${agent}
  [ -f $out/summary.json ] && continue
  mkdir -p $(dirname $out)
  $PY tools/eval.py agent=$agent split=test progress=false hydra.run.dir=$out > $out.log 2>&1 || echo FAIL $out
done
echo ALLDONE
