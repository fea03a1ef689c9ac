#!/bin/bash
# pilot2.sh NAME RULE [extra train args]
name=$1; rule=$2; shift 2
set -e
.venv/bin/scenegen retrieval train --sensor active_stereo --depth-rule $rule --data assets/reference/reference.parquet --shuffle 20 --limit 1000 --out runs/stereo/pilot_$name --quiet "$@"
.venv/bin/scenegen retrieval eval --sensor active_stereo --checkpoint runs/stereo/pilot_$name --scenes assets/panels/v2/panels.json --out runs/stereo/pilot_${name}_val --quiet
