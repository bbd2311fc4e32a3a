"""The command-line package: one module per command, each with ``main(argv) -> int``
(the module docstring is its help), which cli.launch imports and runs for the console
script ``pgt-<name>`` (pyproject.toml) and for headless_scripts/<name>.py, so every
command also runs as
``blender -b [file.blend] -P headless_scripts/<name>.py -- ARGS``.
Benchmarks and developer tools stay in headless_scripts/ and do not ship."""
