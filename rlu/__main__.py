import sys

from rlu.cli import main

sys.exit(main())
