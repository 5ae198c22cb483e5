#!/bin/bash
# TPU VM pod: the same command on every worker; jax.distributed.initialize() discovers the pod by itself.
#   gcloud compute tpus tpu-vm ssh $TPU --zone $ZONE --worker=all --command "cd sc3_jax && bash launch/tpu_vm.sh"
set -euo pipefail
python launch/multihost.py --auto -- train --config "${CONFIG:-paper}" "$@"
