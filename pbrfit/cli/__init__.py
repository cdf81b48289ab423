"""The `pbrfit` command: arguments to options, progress, exit codes (`main`); `pbrfit fit`
(`fit`), the `--model` flag of fit and render (`model_flag`) and `pbrfit demo` (`demo`).

May import every room; nothing imports it. Its modules are not imported here, so that
`pbrfit --help` stays light.
"""
