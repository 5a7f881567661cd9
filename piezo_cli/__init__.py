"""The ``piezo`` command line: a thin dispatcher over the packages."""
