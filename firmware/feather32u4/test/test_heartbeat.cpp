// test_heartbeat.cpp -- STATUS scheduling with a fake clock, across the micros() wrap.
#include "../src/core/heartbeat.h"
#include "runner.h"

using namespace stipi;

TEST(heartbeat_due_at_boot_then_every_period) {
  Heartbeat h(500000);
  CHECK(h.due(0));
  h.sent(0);
  CHECK(!h.due(499999));
  CHECK(h.due(500000));
  h.sent(500300);  // sent a little late: the schedule does not drift
  CHECK(!h.due(999999));
  CHECK(h.due(1000000));
}

TEST(heartbeat_restarts_after_a_long_stall) {
  Heartbeat h(500000);
  h.sent(0);
  h.sent(3000000);  // main loop stalled for 3 s
  CHECK(!h.due(3400000));
  CHECK(h.due(3500000));
}

TEST(heartbeat_survives_micros_wrap) {
  Heartbeat h(500000);
  const uint32_t t = 0xFFFFFFFFu - 100000;
  h.sent(t);
  CHECK(!h.due(t + 499999u));  // wraps past zero
  CHECK(h.due(t + 500000u));
  // every STATUS interval stays within the 1 s the protocol allows, over the wrap
  uint32_t now = t, last = t;
  for (int i = 0; i < 100000; ++i) {
    now += 37;
    if (h.due(now)) {
      CHECK(static_cast<uint32_t>(now - last) <= 1000000u);
      h.sent(now);
      last = now;
    }
  }
}
