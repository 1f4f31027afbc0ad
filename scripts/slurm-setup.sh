#!/usr/bin/env bash
# Runs a single-node Slurm cluster (this host, partition "debug") for the integration test
# and CI. Installs slurm-wlm + munge from Debian, writes a minimal config and starts munged,
# slurmctld and slurmd as plain daemons: the sandbox has no systemd, so no unit files are used.
# Idempotent: when everything already runs with the same config it only checks and exits 0.
#   scripts/slurm-setup.sh          install (if needed), configure, start, wait for "idle"
#   scripts/slurm-setup.sh --stop   stop the three daemons
set -euo pipefail

CONF_DIR=/etc/slurm
LOG_DIR=/var/log/slurm
RUN_DIR=/run/slurm
MUNGE_PID=/run/munge/munged.pid
NODE=$(hostname -s)

say() { echo "slurm-setup: $*"; }
show_logs=0 # set once the slurm daemons are involved, so their errors come with their logs
die() {
  echo "slurm-setup: error: $*" >&2
  ((show_logs)) && for f in "$LOG_DIR/slurmctld.log" "$LOG_DIR/slurmd.log"; do
    [[ -f $f ]] && { echo "--- last lines of $f" >&2; tail -n 15 "$f" >&2; }
  done
  exit 1
}
# Is daemon $1 alive per pidfile $2? The name check guards against a stale pidfile whose pid
# was reused (e.g. after a daemon was killed -9).
pid_of() { cat "$1" 2>/dev/null; }
running() { local pid; pid=$(pid_of "$2") && [[ $(cat "/proc/$pid/comm" 2>/dev/null) == "$1" ]]; }

stop_daemon() { # name pidfile
  local pid
  if running "$1" "$2"; then
    pid=$(pid_of "$2")
    kill "$pid"
    # The daemon removes its own pidfile on exit, so poll the process, not the file.
    for _ in $(seq 100); do [[ -d /proc/$pid ]] || break; sleep 0.2; done
    [[ -d /proc/$pid ]] && die "$1 (pid $pid) did not stop"
    say "stopped $1"
  else
    say "$1 not running"
  fi
  rm -f "$2"
}

stop_all() {
  show_logs=1
  # slurmd first: it reports to slurmctld, and both authenticate through munged.
  stop_daemon slurmd "$RUN_DIR/slurmd.pid"
  stop_daemon slurmctld "$RUN_DIR/slurmctld.pid"
  stop_daemon munged "$MUNGE_PID"
}

[[ $(id -u) == 0 ]] || die "must run as root (installs packages, writes /etc/slurm)"
if [[ ${1:-} == --stop ]]; then
  stop_all
  exit 0
fi
[[ $# == 0 ]] || die "usage: $0 [--stop]"

# --- packages -------------------------------------------------------------------------------
# slurm-wlm pulls in slurmctld, slurmd and slurm-client.
if [[ $(dpkg-query -W -f='${Status}\n' slurm-wlm munge 2>/dev/null | grep -c 'ok installed') != 2 ]]; then
  say "installing slurm-wlm and munge (apt-get)"
  export DEBIAN_FRONTEND=noninteractive
  apt_install() { apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null; }
  # Stale package lists on a fresh machine make the install 404: refresh once and retry.
  apt_install || { apt-get update -qq >/dev/null && apt_install; } || die "apt-get install failed"
else
  say "slurm-wlm and munge already installed"
fi

# --- munge ----------------------------------------------------------------------------------
if [[ ! -s /etc/munge/munge.key ]]; then
  say "creating /etc/munge/munge.key"
  dd if=/dev/urandom bs=1024 count=1 of=/etc/munge/munge.key status=none
fi
chown munge:munge /etc/munge/munge.key && chmod 0400 /etc/munge/munge.key
# /run is normally populated by systemd-tmpfiles; without systemd we create the dirs ourselves.
install -d -o munge -g munge -m 0755 /run/munge
install -d -o munge -g munge -m 0700 /var/lib/munge /var/log/munge
if running munged "$MUNGE_PID"; then
  say "munged already running"
else
  say "starting munged"
  runuser -u munge -- /usr/sbin/munged || die "munged failed to start (see /var/log/munge/munged.log)"
fi
for _ in $(seq 25); do munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
munge -n </dev/null | unmunge >/dev/null || die "munge round trip failed"

# --- slurm.conf -----------------------------------------------------------------------------
# `slurmd -C` reports this machine's CPUs/sockets/cores/RealMemory exactly as slurmd will
# register them; declaring more than that would get the node drained ("Low RealMemory").
HW=$(slurmd -C | sed -n 1p) || die "slurmd -C failed"
[[ $HW == "NodeName=$NODE "* ]] || die "unexpected 'slurmd -C' output: $HW"
mkdir -p "$CONF_DIR" "$LOG_DIR" "$RUN_DIR" /var/spool/slurmd /var/spool/slurmctld
conf=$(cat <<EOF
# Written by motionscale scripts/slurm-setup.sh: single-node cluster on this host.
ClusterName=local
# Loopback addresses: works whether or not the hostname resolves, and never leaves the host.
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
AuthType=auth/munge
MpiDefault=none
# No MTA in the sandbox; the default MailProg makes slurmctld log an error at startup.
MailProg=/bin/true
# No cgroup hierarchy is delegated to us in the sandbox, so track processes by parent pid
# and bind nothing.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
# No slurmdbd: sacct is unavailable; finished jobs stay in "scontrol show job" for MinJobAge.
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
# Cores only (not memory) are consumable, so small jobs run side by side on the node.
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
# A node that was down (e.g. after a restart) comes back as soon as slurmd registers.
ReturnToService=2
MinJobAge=600
SlurmctldPidFile=$RUN_DIR/slurmctld.pid
SlurmdPidFile=$RUN_DIR/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
$HW NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
)
changed=0
if [[ ! -f $CONF_DIR/slurm.conf ]] || [[ $(cat "$CONF_DIR/slurm.conf") != "$conf" ]]; then
  say "writing $CONF_DIR/slurm.conf ($HW)"
  printf '%s\n' "$conf" >"$CONF_DIR/slurm.conf"
  changed=1
fi
show_logs=1
if [[ $changed == 0 ]]; then
  say "$CONF_DIR/slurm.conf unchanged"
elif running slurmctld "$RUN_DIR/slurmctld.pid" || running slurmd "$RUN_DIR/slurmd.pid"; then
  say "config changed: restarting slurm daemons"
  stop_daemon slurmd "$RUN_DIR/slurmd.pid"
  stop_daemon slurmctld "$RUN_DIR/slurmctld.pid"
fi

# --- daemons --------------------------------------------------------------------------------
if running slurmctld "$RUN_DIR/slurmctld.pid"; then
  say "slurmctld already running"
else
  say "starting slurmctld"
  slurmctld || die "slurmctld failed to start"
fi
for _ in $(seq 50); do scontrol ping >/dev/null 2>&1 && break; sleep 0.2; done
scontrol ping >/dev/null 2>&1 || die "slurmctld does not answer 'scontrol ping'"
if running slurmd "$RUN_DIR/slurmd.pid"; then
  say "slurmd already running"
else
  say "starting slurmd"
  slurmd || die "slurmd failed to start"
fi

# --- wait for the node ----------------------------------------------------------------------
state=
for i in $(seq 60); do
  state=$(sinfo -h -n "$NODE" -o %T 2>/dev/null | sed -n 1p) || state=
  case $state in
    idle | mixed | allocated | completing) break ;;
    down* | drain* | fail*)
      # Left over from an earlier run (e.g. a killed slurmd); the config was just checked.
      if ((i % 5 == 1)); then
        say "node $NODE is $state: resuming"
        scontrol update nodename="$NODE" state=resume || true
      fi ;;
  esac
  sleep 0.5
done
case $state in
  idle | mixed | allocated | completing) say "ready: node $NODE is $state in partition debug" ;;
  *) die "node $NODE did not become idle (state: '${state:-none}'; reason: $(sinfo -h -n "$NODE" -o %E))" ;;
esac
