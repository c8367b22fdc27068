"""Capture: drive cameras and projectors, verify every frame, write scan folders.

Sits on top of the package beside :mod:`telefringe.cli`: nothing else imports it. The
contract every driver follows is in :mod:`telefringe.acquisition.base`; the drivers
(``drivers/``) are imported only when a capture asks for them.
"""
