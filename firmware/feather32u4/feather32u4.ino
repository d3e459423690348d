// feather32u4.ino -- STIP-I probe firmware for the Adafruit Feather 32u4 Bluefruit LE.
//
// Thin sketch: builds the hardware glue (src/hal_avr.*) and hands it to the portable core
// (src/core/probe.*), which speaks the binary protocol of docs/protocol.md on every link:
// USB CDC `Serial`, hardware UART `Serial1` at STIPI_UART1_BAUD, and BLE UART via the nRF51822.
// Pins, rates and sizes: config.h. Build/flash: Makefile, docs/firmware.md.
#include <Arduino.h>

#include "config.h"
#include "src/core/probe.h"
#include "src/core/sdep.h"
#include "src/hal_avr.h"

namespace {
stipi::AvrClock g_clock;
stipi::AvrBoard g_board;
stipi::AvrEeprom g_eeprom;
stipi::Probe g_probe(g_clock, g_board, stipi::g_sampler, g_eeprom);
#if STIPI_LINK_USB
stipi::UsbCdcLink g_usb;
#endif
#if STIPI_LINK_UART1
stipi::Uart1Link g_uart1;
#endif
#if STIPI_LINK_BLE
stipi::AvrSpiPort g_spi;
stipi::SdepDriver g_sdep(g_spi, g_clock);
stipi::BleUartLink g_ble(g_sdep, g_spi, g_clock);
#endif
}  // namespace

void setup() {
  g_board.begin_watchdog();
  g_board.begin();
#if STIPI_LINK_USB
  Serial.begin(115200);  // baud is ignored by USB CDC
  g_probe.set_link(stipi::kLinkUsb, &g_usb);
#endif
#if STIPI_LINK_UART1
  Serial1.begin(STIPI_UART1_BAUD);
  g_probe.set_link(stipi::kLinkUart, &g_uart1);
#endif
#if STIPI_LINK_BLE
  g_spi.begin();
  g_ble.begin();
  g_probe.set_link(stipi::kLinkBle, &g_ble);
#endif
  g_probe.set_reset_cause(g_board.reset_cause());
  g_probe.begin();
}

void loop() {
  g_board.kick_watchdog();
#if STIPI_LINK_BLE
  g_ble.poll();
  g_probe.set_ble_health(g_ble.health(), g_ble.module_resets());
#endif
  g_probe.poll();
}
