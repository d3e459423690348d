"""BLE: the probe's Nordic UART link on real Bluetooth stacks, with no radio needed in tests.

:mod:`.nus` (service UUIDs, advertising payloads), :mod:`.module` (pure model of the
Bluefruit module's transmit buffer, connection-event pacing and notification faults),
:mod:`.radio` (HCI endpoints: a USB dongle, an HCI socket or an in-process virtual radio of
Bumble software controllers), :mod:`.peripheral` (the module as a Bumble peripheral with
fault injection), :mod:`.mock_probe` (the firmware model streaming through it) and
:mod:`.bleak_backend` (a bleak backend on Bumble's host stack, so bleak's public API runs
over a dongle or a virtual radio). The daemon's BLE transport is
:mod:`stipi_daemon.probe.transports.ble`. Nothing here is imported until used: Bumble and bleak
load only when a BLE link is opened.
"""
