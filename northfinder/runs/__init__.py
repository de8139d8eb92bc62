"""Runs: one module per kind of run — live measurement, result assembly and replay — on one small
shared base (northfinder.runs.base). Below the CLI, above the sequencer and the run directory.

- `find`: the turntable find (northfinder find, find --resume, replay of a find run);
- `campaign`: N finds in a row at one or more base headings (northfinder campaign), each one a
  `find` run (northfinder.runs.find.run_find); its statistics are pure numpy and sit with the
  estimators (northfinder.estimators.campaign_stats), its tables and figure with the CLI
  (northfinder.cli._campaign_report).
- `swaying`: align --mode swaying (IMU alone on a swaying base), its result and replay;
- `gnss` (result, time alignment, replay) and `gnss_live` (reading the IMU and the GNSS receiver
  together): align --mode gnss. The mathematics they call is in northfinder.align.
"""
