// crc16.h -- CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR).
// Owns the frame checksum of docs/protocol.md; nothing else. Check value of "123456789": 0x29B1.
#ifndef STIPI_CORE_CRC16_H
#define STIPI_CORE_CRC16_H

#include <stdint.h>

namespace stipi {

const uint16_t kCrcInit = 0xFFFF;

// Continue a CRC over `len` bytes (start with kCrcInit).
uint16_t crc16_update(uint16_t crc, const uint8_t* data, uint16_t len);

inline uint16_t crc16(const uint8_t* data, uint16_t len) { return crc16_update(kCrcInit, data, len); }

}  // namespace stipi

#endif
