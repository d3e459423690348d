// test_cal_store.cpp -- EEPROM calibration record: round trip, corruption, torn writes.
#include "../src/core/cal_store.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

TEST(cal_store_blank_eeprom_is_invalid) {
  fakes::FakeEeprom e;
  CalStore store(e, 0);
  Calibration c = {1, 2};
  CHECK(!store.load(c));
  CHECK_EQ(c.zero_counts, 0);
  CHECK_EQ(c.span_un_per_count, 0);
  CHECK_EQ(store.slot_state(0, nullptr, nullptr), kSlotBadMagic);
}

TEST(cal_store_round_trip_and_alternating_slots) {
  fakes::FakeEeprom e;
  CalStore store(e, 100);
  Calibration a = {512, -123456};
  CHECK(store.store(a));
  Calibration r = {};
  CHECK(store.load(r));
  CHECK_EQ(r.zero_counts, 512);
  CHECK_EQ(r.span_un_per_count, -123456);
  CHECK_EQ(e.mem[100], 0x53);  // magic "ST" little-endian, at the base address
  CHECK_EQ(e.mem[101], 0x54);
  for (int i = 0; i < 300; ++i) {  // generations wrap at 256
    Calibration c = {static_cast<uint16_t>(i % 1024), i + 1};
    CHECK(store.store(c));
    CHECK(store.load(r));
    CHECK_EQ(r.zero_counts, c.zero_counts);
    CHECK_EQ(r.span_un_per_count, c.span_un_per_count);
  }
}

TEST(cal_store_detects_corruption_and_falls_back_to_the_other_slot) {
  fakes::FakeEeprom e;
  CalStore store(e, 0);
  Calibration a = {100, 1000};
  Calibration b = {200, 2000};
  CHECK(store.store(a));  // slot 0
  CHECK(store.store(b));  // slot 1 (newer)
  e.mem[kCalSlotLen + 5] ^= 0x10;  // flip a bit in slot 1's zero_counts
  CHECK_EQ(store.slot_state(1, nullptr, nullptr), kSlotBadCrc);
  Calibration r = {};
  CHECK(store.load(r));
  CHECK_EQ(r.zero_counts, 100);  // the older intact record
  e.mem[2] = 9;  // slot 0 version
  CHECK_EQ(store.slot_state(0, nullptr, nullptr), kSlotBadVersion);
  CHECK(!store.load(r));
}

TEST(cal_store_torn_write_keeps_previous_record) {
  fakes::FakeEeprom e;
  CalStore store(e, 0);
  Calibration a = {300, 3000};
  CHECK(store.store(a));
  e.writes_left = 5;  // power fails after 5 bytes of the next record
  Calibration b = {400, 4000};
  CHECK(!store.store(b));  // readback detects the failed write
  Calibration r = {};
  CHECK(store.load(r));
  CHECK_EQ(r.zero_counts, 300);
  CHECK_EQ(r.span_un_per_count, 3000);
}

TEST(cal_store_writes_only_changed_bytes) {
  fakes::FakeEeprom e;
  CalStore store(e, 0);
  Calibration a = {1, 1};
  CHECK(store.store(a));
  CHECK(store.store(a));  // slot 1
  const int before = e.writes;
  CHECK(store.store(a));  // slot 0 again: only the generation and CRC bytes change
  CHECK(e.writes - before <= 3);
}
