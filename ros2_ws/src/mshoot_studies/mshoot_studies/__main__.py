"""``python -m mshoot_studies``: the ``mshoot`` command."""
import sys

from mshoot_studies.cli import main

if __name__ == '__main__':
    sys.exit(main())
