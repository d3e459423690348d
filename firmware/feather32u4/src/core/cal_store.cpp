// cal_store.cpp -- two-slot EEPROM calibration record (see cal_store.h).
#include "cal_store.h"

#include "crc16.h"
#include "frame.h"

namespace stipi {

CalSlotState CalStore::slot_state(uint8_t slot, Calibration* cal, uint8_t* generation) {
  uint8_t b[kCalSlotLen];
  const uint16_t addr = static_cast<uint16_t>(base_ + slot * kCalSlotLen);
  for (uint8_t i = 0; i < kCalSlotLen; ++i) b[i] = eeprom_.read(static_cast<uint16_t>(addr + i));
  if (get_u16(b) != kCalMagic) return kSlotBadMagic;
  if (b[2] != kCalVersion) return kSlotBadVersion;
  if (crc16(b, 10) != get_u16(b + 10)) return kSlotBadCrc;
  if (generation) *generation = b[3];
  if (cal) {
    cal->zero_counts = get_u16(b + 4);
    cal->span_un_per_count = static_cast<int32_t>(get_u32(b + 6));
  }
  return kSlotValid;
}

int8_t CalStore::newest_slot(uint8_t* generation) {
  uint8_t g0 = 0, g1 = 0;
  const bool v0 = slot_state(0, 0, &g0) == kSlotValid;
  const bool v1 = slot_state(1, 0, &g1) == kSlotValid;
  if (v0 && v1) {
    // Generations wrap: slot 1 is newer when it is ahead by 1..127.
    const bool one_newer = static_cast<int8_t>(static_cast<uint8_t>(g1 - g0)) > 0;
    *generation = one_newer ? g1 : g0;
    return one_newer ? 1 : 0;
  }
  if (v0) {
    *generation = g0;
    return 0;
  }
  if (v1) {
    *generation = g1;
    return 1;
  }
  return -1;
}

bool CalStore::load(Calibration& out) {
  uint8_t gen = 0;
  const int8_t slot = newest_slot(&gen);
  out.zero_counts = 0;
  out.span_un_per_count = 0;
  if (slot < 0) return false;
  slot_state(static_cast<uint8_t>(slot), &out, 0);
  return true;
}

bool CalStore::store(const Calibration& cal) {
  uint8_t gen = 0;
  const int8_t newest = newest_slot(&gen);
  const uint8_t slot = newest == 0 ? 1 : 0;
  uint8_t b[kCalSlotLen];
  put_u16(b, kCalMagic);
  b[2] = kCalVersion;
  b[3] = newest < 0 ? 0 : static_cast<uint8_t>(gen + 1);
  put_u16(b + 4, cal.zero_counts);
  put_u32(b + 6, static_cast<uint32_t>(cal.span_un_per_count));
  put_u16(b + 10, crc16(b, 10));
  const uint16_t addr = static_cast<uint16_t>(base_ + slot * kCalSlotLen);
  for (uint8_t i = 0; i < kCalSlotLen; ++i) {
    const uint16_t a = static_cast<uint16_t>(addr + i);
    if (eeprom_.read(a) != b[i]) eeprom_.write(a, b[i]);  // update only: saves wear
  }
  for (uint8_t i = 0; i < kCalSlotLen; ++i) {
    if (eeprom_.read(static_cast<uint16_t>(addr + i)) != b[i]) return false;
  }
  return true;
}

}  // namespace stipi
