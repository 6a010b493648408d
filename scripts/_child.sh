# Sourced by the scripts that run a recipe for hours (main_job.sh, ablations.sh, long_ablations.sh).
# `child CMD...` runs CMD as the script's child and passes a SIGTERM or SIGINT sent to the script on to it as
# SIGTERM, so that stopping the script (kill PID, a job manager, Ctrl-C) stops the recipe's running stage, which
# saves its checkpoint, instead of leaving the recipe running without its script. It returns CMD's exit status
# (143 after SIGTERM), so a script under `set -e` stops there too.
child() {
  "$@" &
  _child_pid=$!
  trap 'kill -TERM "$_child_pid" 2>/dev/null || true' TERM INT
  local status=0
  # a trapped signal ends `wait` early (status > 128) with the child still running: wait again for its own status
  while kill -0 "$_child_pid" 2>/dev/null; do
    status=0
    wait "$_child_pid" || status=$?
  done
  trap - TERM INT
  return "$status"
}
