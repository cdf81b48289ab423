"""The `pbrfit` command: arguments to options, progress, exit codes (`main`); `pbrfit fit`
(`fit`), the `--model` flag of fit and render (`model_flag`) and `pbrfit demo` (`demo`).

May import every room; nothing imports it. Its modules import what they use at their heads:
the parser takes the options' defaults from the rooms that own them, so every command, even
``--help``, loads the fit's stack (JAX, optimistix) before it parses.
"""
