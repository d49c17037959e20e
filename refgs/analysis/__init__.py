"""The analysis floor: reads finished run directories (through ``refgs.runs``) and writes tables
with statistics, flatness curves, figures, committable records and the speed/error bench.

Nothing here trains; nothing below this floor imports it."""
