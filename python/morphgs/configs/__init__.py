"""Run configs shipped with morphgs, one per registered model (`<name>.toml`), read with
`morphgs.models.registry.default_config_text(name)`."""
