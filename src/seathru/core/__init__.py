"""The shared numerical core: pure functions and modules, no file I/O."""
