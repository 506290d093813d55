"""Allow ``python -m msctl``."""

from msctl.cli import main

main()
