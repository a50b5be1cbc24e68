#!/bin/sh
# Container entry point: runs `tiltlab serve` unless told otherwise.
#   (no arguments)          tiltlab serve
#   --port 9000 ...         tiltlab serve --port 9000 ...   (options go to serve)
#   db upgrade, token ...   that tiltlab command
#   tiltlab ARGS            tiltlab ARGS
#   sh, id, python ...      that program (any other word that names a program on the PATH)
# tiltlab (or the program) replaces this shell (exec), so it receives the container's stop signal directly.
set -eu
# tiltlab's commands (`tiltlab --help`); a test keeps this list equal to them
TILTLAB_COMMANDS="calibrate correct db devices discrepancy level plan reproduce serve sim simulate token verify-certificate"
if [ "$#" -eq 0 ]; then
    set -- serve
fi
case "$1" in
    tiltlab) shift ;;
    -*) set -- serve "$@" ;;
    *)
        case " $TILTLAB_COMMANDS " in
            *" $1 "*) ;;
            *) if command -v "$1" >/dev/null 2>&1; then exec "$@"; fi ;;
        esac
        ;;
esac
exec tiltlab "$@"
