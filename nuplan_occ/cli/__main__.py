"""`python -m nuplan_occ.cli`: the same as the `nuplan-occ` command."""

from nuplan_occ.cli.app import main

main()
