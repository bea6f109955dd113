import sys

from keyshape.cli import main

sys.exit(main())
