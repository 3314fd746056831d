"""One module per ``mocap-labeler`` command (see ``labeler_service.cli.main``)."""
