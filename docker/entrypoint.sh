#!/bin/sh
# Container entry point: runs `tiltlab serve` unless told otherwise.
#   (no arguments)          tiltlab serve
#   --port 9000 ...         tiltlab serve --port 9000 ...   (options go to serve)
#   db upgrade, token ...   that tiltlab command
#   tiltlab ARGS            tiltlab ARGS
# tiltlab replaces this shell (exec), so it receives the container's stop signal directly.
set -eu
if [ "$#" -eq 0 ]; then
    set -- serve
fi
case "$1" in
    tiltlab) shift ;;
    -*) set -- serve "$@" ;;
esac
exec tiltlab "$@"
