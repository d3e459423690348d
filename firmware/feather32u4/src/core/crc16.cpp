// crc16.cpp -- bitwise CRC-16/CCITT-FALSE (no 512-byte table: flash is scarce on the 32u4).
#include "crc16.h"

namespace stipi {

uint16_t crc16_update(uint16_t crc, const uint8_t* data, uint16_t len) {
  for (uint16_t i = 0; i < len; ++i) {
    crc ^= static_cast<uint16_t>(static_cast<uint16_t>(data[i]) << 8);
    for (uint8_t bit = 0; bit < 8; ++bit) {
      crc = (crc & 0x8000u) ? static_cast<uint16_t>((crc << 1) ^ 0x1021u)
                            : static_cast<uint16_t>(crc << 1);
    }
  }
  return crc;
}

}  // namespace stipi
