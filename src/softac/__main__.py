import sys

from softac.cli import main

sys.exit(main())
