#!/usr/bin/env bash
# A one-node SLURM cluster on this machine (slurmctld + slurmd on localhost, munge for authentication),
# for tests/workflow/test_slurm.py and for trying workflow/profiles/slurm by hand. Run as root:
#   bash tests/slurm/start.sh     # install (first time), configure, start; waits until the node is idle
#   bash tests/slurm/stop.sh      # stop the daemons (the packages and the config stay)
# A second call while the cluster is up changes nothing. Debian/Ubuntu (apt) only.
#
# What it configures (/etc/slurm/slurm.conf, docs/cluster.md):
#   - one node named after this machine with its real CPU count and memory (from `slurmd -C`);
#   - CPUs and memory are consumable (select/cons_tres, CR_CPU_Memory): a job gets --cpus-per-task
#     CPUs and --mem MB of the node, and jobs that do not fit wait;
#   - memory is enforced by jobacct_gather/linux with OverMemoryKill (a step above its --mem is killed;
#     cgroups are not used: ProctrackType=proctrack/linuxproc, TaskPlugin=task/none work in containers);
#   - time limits (--time) are enforced by slurmctld (KillWait 5 s after the limit);
#   - no accounting database (AccountingStorageType=accounting_storage/none, so `sacct` has nothing):
#     finished jobs stay visible to `squeue`/`scontrol show job` for MinJobAge=3600 s, which is what
#     the Snakemake executor plugin falls back to for job states.
set -euo pipefail

log() { echo "[slurm start] $*"; }
die() { echo "[slurm start] error: $*" >&2; exit 1; }

[ "$(id -u)" -eq 0 ] || die "run as root (it installs packages and starts daemons)."

CONF=/etc/slurm/slurm.conf
MARK="# written by trace3d tests/slurm/start.sh"

node_idle() {
  timeout 10 sinfo -h -N -o '%T' 2>/dev/null | grep -qE '^(idle|mixed|allocated)'
}

# Already up with our config: nothing to do.
if [ -f "$CONF" ] && grep -qF "$MARK" "$CONF" && pgrep -x slurmctld >/dev/null && pgrep -x slurmd >/dev/null \
   && pgrep -x munged >/dev/null && node_idle; then
  log "cluster already up: $(sinfo -h -N -o '%N %T %c CPUs %m MB')"
  exit 0
fi

# 1. Packages (apt-get update once per call, only when something is missing).
need=()
for cmd in slurmctld slurmd sbatch munged; do
  command -v "$cmd" >/dev/null || need+=("$cmd")
done
if [ "${#need[@]}" -gt 0 ]; then
  command -v apt-get >/dev/null || die "missing ${need[*]} and no apt-get to install slurmctld slurmd slurm-client munge."
  log "installing slurmctld slurmd slurm-client munge"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq slurmctld slurmd slurm-client munge >/dev/null
fi

# 2. munge: a random key (kept if one is there), munged as the munge user.
install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
install -d -o munge -g munge -m 0755 /run/munge
if [ ! -s /etc/munge/munge.key ]; then
  log "new random /etc/munge/munge.key"
  dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown munge:munge /etc/munge/munge.key
chmod 0400 /etc/munge/munge.key
if ! pgrep -x munged >/dev/null; then
  log "starting munged"
  runuser -u munge -- /usr/sbin/munged
fi
for _ in $(seq 20); do
  munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
  sleep 0.5
done
munge -n | unmunge >/dev/null || die "munge does not work (see /var/log/munge/munged.log)."

# 3. slurm.conf: this machine's name, CPUs and memory.
host=$(hostname -s)
cpus=$(nproc --all)
# slurmd -C reports what slurmd itself will measure at registration; a RealMemory above that drains the node
mem=$(slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p')
[ -n "$mem" ] || mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 ))
install -d -m 0755 /etc/slurm /var/spool/slurmctld /var/spool/slurmd /var/log/slurm /run/slurm
new=$(mktemp)
cat > "$new" <<CONF_EOF
$MARK
ClusterName=trace3d
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldPidFile=/run/slurm/slurmctld.pid
SlurmdPidFile=/run/slurm/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=task=2
JobAcctGatherParams=OverMemoryKill
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MinJobAge=3600
KillWait=5
ReturnToService=2
SlurmctldTimeout=30
SlurmdTimeout=30
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF_EOF
restart=0
if ! cmp -s "$new" "$CONF"; then
  log "writing $CONF (node $host: $cpus CPUs, $mem MB)"
  install -m 0644 "$new" "$CONF"
  restart=1
fi
rm -f "$new"

# 4. The daemons, as root; restarted when the config changed.
if [ "$restart" -eq 1 ]; then
  for d in slurmd slurmctld; do
    if pid=$(pgrep -x "$d"); then
      log "stopping old $d ($pid)"
      kill $pid
      for _ in $(seq 20); do kill -0 $pid 2>/dev/null || break; sleep 0.5; done
    fi
  done
fi
if ! pgrep -x slurmctld >/dev/null; then
  log "starting slurmctld"
  /usr/sbin/slurmctld
fi
if ! pgrep -x slurmd >/dev/null; then
  log "starting slurmd"
  /usr/sbin/slurmd
fi

# 5. Wait for the node to register idle (a node left down/drained by an earlier run is resumed).
for i in $(seq 60); do
  if node_idle; then
    log "cluster up: $(sinfo -h -N -o '%N %T %c CPUs %m MB')"
    exit 0
  fi
  state=$(timeout 10 sinfo -h -N -o '%T' 2>/dev/null || true)
  case "$state" in
    down*|drain*) scontrol update NodeName="$host" State=RESUME >/dev/null 2>&1 || true ;;
  esac
  sleep 1
done
die "node $host not idle after 60 s (sinfo: $(sinfo -h -N -o '%N %T %E' 2>&1)); see /var/log/slurm/slurmctld.log and slurmd.log."
