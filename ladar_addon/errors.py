"""User-facing errors of the Blender side (bad scene set-up); settings errors are core ``ConfigError``s."""


class LadarError(Exception):
    """The scene cannot be simulated as set up (no sensor, no geometry, unsaved file for a relative path...).

    The message is one line that tells the user what to change.
    """
