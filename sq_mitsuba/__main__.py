import sys

from sq_mitsuba.cli import main

sys.exit(main())
