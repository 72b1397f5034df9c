#!/bin/bash
# run.sh NAME cmd... : run a case, keep its stdout/stderr in logs/NAME.{out,err}, print the
# command, exit code, process CPU seconds (user, sys) and the last stderr lines.
name=$1; shift
mkdir -p logs
/usr/bin/time -f "%U %S" -o logs/$name.time nice -n 5 "$@" > logs/$name.out 2> logs/$name.err
rc=$?
echo "### $name rc=$rc cpu=$(tail -1 logs/$name.time) :: $*"
grep -v "^\[" logs/$name.err | grep -v "^  " | tail -3
