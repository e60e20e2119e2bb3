"""multislit.app: the command line, the demo and its figures."""
