// test_sampler.cpp -- ring buffer overflow accounting, first_index continuity, timestamps.
#include "../src/core/sampler.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

TEST(sampler_batches_keep_index_and_time_continuous) {
  Sampler s;
  s.set_period(10000);
  for (uint32_t i = 0; i < 25; ++i) s.isr_push(static_cast<uint16_t>(i), 5000 + i * 10000);
  Batch b;
  CHECK_EQ(s.pop(b, 10), 10);
  CHECK_EQ(b.first_index, 0u);
  CHECK_EQ(b.t_us, 5000u);
  CHECK_EQ(b.adc[9], 9);
  CHECK_EQ(s.pop(b, 10), 10);
  CHECK_EQ(b.first_index, 10u);
  CHECK_EQ(b.t_us, 105000u);  // t of sample 10 = t0 + 10 * period
  CHECK_EQ(b.adc[0], 10);
  CHECK_EQ(s.pop(b, 10), 5);
  CHECK_EQ(b.first_index, 20u);
  CHECK_EQ(b.period_us, 10000);
  CHECK_EQ(s.available(), 0);
  CHECK_EQ(s.dropped(), 0u);
  CHECK_EQ(s.taken(), 25u);
  CHECK_EQ(fakes::irq_depth(), 0);  // every critical section closed
}

TEST(sampler_overflow_drops_until_empty_and_counts_every_sample) {
  Sampler s;
  s.set_period(1000);
  const uint32_t cap = Sampler::kCapacity;
  for (uint32_t i = 0; i < cap + 5; ++i) s.isr_push(static_cast<uint16_t>(i), i * 1000);
  CHECK_EQ(s.available(), cap);
  CHECK_EQ(s.dropped(), 5u);
  Batch b;
  CHECK_EQ(s.pop(b, 10), 10);  // room again, but the ring is not empty: still dropping
  s.isr_push(999, 0);
  CHECK_EQ(s.dropped(), 6u);
  CHECK_EQ(s.available(), cap - 10);
  uint32_t expect = 10;
  while (s.pop(b, 16) > 0) {
    CHECK_EQ(b.first_index, expect);  // queued samples stay consecutive
    expect += b.count;
  }
  CHECK_EQ(expect, cap);
  // first sample after the drain: index = taken so far, time re-anchored to its own t
  const uint32_t next = s.taken();
  s.isr_push(5, 123456789);
  CHECK_EQ(s.pop(b, 10), 1);
  CHECK_EQ(b.first_index, next);
  CHECK_EQ(b.t_us, 123456789u);
  // host accounting: gap between batches == samples dropped in the probe
  CHECK_EQ(next - cap, s.dropped());
}

TEST(sampler_isr_drop_counts_and_keeps_ring_contiguous) {
  Sampler s;
  s.set_period(1000);
  s.isr_drop();  // empty ring: just counted
  s.isr_push(1, 1000);
  s.isr_drop();  // non-empty: following samples wait for the drain
  s.isr_push(2, 3000);
  Batch b;
  CHECK_EQ(s.pop(b, 10), 1);
  CHECK_EQ(b.first_index, 1u);
  CHECK_EQ(s.dropped(), 3u);
  s.isr_push(3, 4000);
  CHECK_EQ(s.pop(b, 10), 1);
  CHECK_EQ(b.first_index, 4u);
}

TEST(sampler_timestamps_wrap_with_micros) {
  Sampler s;
  s.set_period(1000);
  const uint32_t t0 = 0xFFFFFC18u;  // 1000 us before the 2^32 wrap
  for (uint32_t i = 0; i < 4; ++i) s.isr_push(static_cast<uint16_t>(i), t0 + i * 1000);
  Batch b;
  CHECK_EQ(s.pop(b, 2), 2);
  CHECK_EQ(b.t_us, t0);
  CHECK_EQ(s.pop(b, 2), 2);
  CHECK_EQ(b.t_us, 1000u);  // t0 + 2000 mod 2^32
}

TEST(sampler_clear_discards_without_touching_indices) {
  Sampler s;
  s.set_period(1000);
  for (int i = 0; i < 5; ++i) s.isr_push(1, 0);
  s.clear();
  CHECK_EQ(s.available(), 0);
  CHECK_EQ(s.taken(), 5u);
  s.isr_push(1, 77);
  Batch b;
  s.pop(b, 10);
  CHECK_EQ(b.first_index, 5u);
  CHECK_EQ(b.t_us, 77u);
}
