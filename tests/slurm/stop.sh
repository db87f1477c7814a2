#!/usr/bin/env bash
# Stops the one-node cluster that tests/slurm/start.sh started (slurmd, slurmctld, munged), as root.
# Packages, /etc/slurm/slurm.conf and the munge key stay, so start.sh brings it back without apt.
set -uo pipefail
[ "$(id -u)" -eq 0 ] || { echo "[slurm stop] error: run as root." >&2; exit 1; }
for d in slurmd slurmctld munged; do
  pids=$(pgrep -x "$d") || continue
  echo "[slurm stop] stopping $d ($pids)"
  kill $pids
  for _ in $(seq 20); do
    alive=0
    for p in $pids; do kill -0 "$p" 2>/dev/null && alive=1; done
    [ "$alive" -eq 0 ] && break
    sleep 0.5
  done
done
exit 0
