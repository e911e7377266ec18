"""The wheelgrid command, parameter files and launch description for the whole chain."""
