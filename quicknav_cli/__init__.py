"""The `quicknav` command line (``quicknav_cli.main:app``): the one place that imports the library,
the service and the SDK together. The library (``quicknav_core``) never imports it."""
