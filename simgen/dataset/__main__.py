"""``python -m simgen.dataset generate SPEC --out DIR [--time-budget S] [--report R.json]`` and ``check DIR``:
the dataset commands without typer or rich (for machines that lack them)."""

import sys

from simgen.dataset._cli import main

sys.exit(main())
