"""The emulated BLE probe: the probe's Nordic UART link with no radio or probe needed.

:mod:`.module` (pure model of the Bluefruit module's transmit buffer, connection-event
pacing and notification faults), :mod:`.radio` (HCI endpoints: a USB dongle, an HCI
socket or an in-process virtual radio of Bumble software controllers), :mod:`.peripheral`
(the module as a Bumble peripheral with fault injection), :mod:`.mock_probe` (the firmware
model streaming through it), :mod:`.mock_peripheral` (``mock-peripheral``'s serving loop
with periodic faults), :mod:`.emulation` (an emulated probe started for the daemon's
BLE transport) and :mod:`.bleak_backend` (a bleak backend on Bumble's host stack, so
bleak's public API runs over a dongle or a virtual radio). The daemon's real BLE transport
is :mod:`stipi_daemon.probe.transports.ble` and the service UUIDs are
:mod:`stipi_daemon.probe.nus`; the transport reaches this package only by name through
:mod:`stipi_daemon.registry`. Nothing here is imported until used: Bumble loads only when an
emulated link is opened.
"""
