"""Bad input for every command: one file per command (fit, convert, discrepancy, improve,
sweep). A package, so that its module names do not clash with tests/test_<command>.py."""
