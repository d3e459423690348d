// cdc_write.h -- how many queued bytes to hand the Arduino core's USB CDC now, so that its
// USB_Send() never waits and never fails after it has queued bytes.
//
// Owns: the rule only; the glue (hal_avr.cpp) supplies the core's Serial and the SOF interrupt
// enable, the host tests a model of the core's code (tests/firmware/usb_core_model).
// Why (Arduino core USBCore.cpp USB_Send): a write that fills the endpoint bank exactly makes
// USB_Send release it and then insist on a zero-length packet, which needs the OTHER bank; with
// a host that has not read that one, USB_Send waits up to 250 ms (delay(1) x 250) and returns
// -1 although the bytes are queued -- a caller that trusts the -1 sends them again. And the SOF
// interrupt flushes the bank (USB_Flush) at any moment, so the room availableForWrite() saw may
// be gone (the other bank still full) when USB_Send looks again: the same 250 ms wait.
// The rule: with the SOF interrupt held off, hand over at most room - 1 bytes. The bank is
// never full (no release, no zero-length packet inside USB_Send) and the room cannot change
// between the check and the write; the next SOF sends the bank.
#ifndef STIPI_CORE_CDC_WRITE_H
#define STIPI_CORE_CDC_WRITE_H

#include <stdint.h>

namespace stipi {

// Cdc: hold_sof(bool), available_for_write() -> int, write(data, n) -> bytes taken.
template <typename Cdc>
uint16_t cdc_write(Cdc& cdc, const uint8_t* data, uint16_t n) {
  cdc.hold_sof(true);
  const int room = cdc.available_for_write();
  uint16_t sent = 0;
  if (room > 1) {
    const uint16_t k = n < static_cast<uint16_t>(room - 1) ? n : static_cast<uint16_t>(room - 1);
    const int took = static_cast<int>(cdc.write(data, k));
    sent = took > 0 ? static_cast<uint16_t>(took) : 0;
  }
  cdc.hold_sof(false);
  return sent;
}

}  // namespace stipi

#endif
