// Adafruit_BLEMIDI.h -- stand-in for the library's MIDI helper (not under test, not shipped in
// ../shared/reference): the one static function Adafruit_BLE.cpp refers to.
#ifndef STIPI_SHIM_BLEMIDI_H
#define STIPI_SHIM_BLEMIDI_H
#include <stdint.h>
class Adafruit_BLEMIDI {
 public:
  template <typename F>
  static void processRxCallback(uint8_t*, uint16_t, F) {}
};
#endif
