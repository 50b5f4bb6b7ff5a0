"""The application core: one function per user action (`actions`), the documents they answer with
(`documents`), and the rig worker that plays runs on one open rig (`worker`, `events`).

The command line (`rig.cli`) and the REST service (`api`) are thin shells over this package.
"""
