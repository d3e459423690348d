// cal_store.h -- EEPROM layout of the tare/calibration record.
//
// Owns: the byte layout, validation (magic, version, CRC) and the two-slot update that keeps the
// previous record if power fails in the middle of a write. Does not own what the numbers mean
// (the host computes force_n = (adc - zero_counts) * span_un_per_count * 1e-6).
//
// Layout (little-endian), two slots of kCalSlotLen bytes from STIPI_EEPROM_CAL_ADDR:
//   +0  magic u16 = 0x5453 ("ST")   +2 version u8 = 1   +3 generation u8 (wraps; newer wins)
//   +4  zero_counts u16             +6 span_un_per_count i32
//   +10 crc16 u16 over bytes 0..9 (CRC-16/CCITT-FALSE)
// A write goes to the slot that does not hold the newest valid record, with generation + 1.
#ifndef STIPI_CORE_CAL_STORE_H
#define STIPI_CORE_CAL_STORE_H

#include <stdint.h>

#include "hal.h"

namespace stipi {

const uint16_t kCalMagic = 0x5453;
const uint8_t kCalVersion = 1;
const uint8_t kCalSlotLen = 12;

struct Calibration {
  uint16_t zero_counts;        // ADC counts at zero force
  int32_t span_un_per_count;   // force per ADC count [uN/count]; 0 = not calibrated
};

enum CalSlotState : uint8_t { kSlotValid = 0, kSlotBadMagic, kSlotBadVersion, kSlotBadCrc };

class CalStore {
 public:
  CalStore(Eeprom& eeprom, uint16_t base_addr) : eeprom_(eeprom), base_(base_addr) {}

  // Read both slots; true and `out` = the newest valid record, false (out zeroed) if none.
  bool load(Calibration& out);
  // Write `cal` into the older slot and read it back; false if the readback differs.
  bool store(const Calibration& cal);
  // Inspect one slot (0 or 1), for diagnostics and tests.
  CalSlotState slot_state(uint8_t slot, Calibration* cal, uint8_t* generation);

 private:
  int8_t newest_slot(uint8_t* generation);  // -1 when no slot is valid
  Eeprom& eeprom_;
  uint16_t base_;
};

}  // namespace stipi

#endif
