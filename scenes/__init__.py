"""Built-in scene files (TOML), addressable by name: ``softsim run jelly_drop``."""
