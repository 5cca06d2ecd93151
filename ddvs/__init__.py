"""The `ddvs` command: the top of the dependency graph, importing a subcommand's module only when it runs."""
