// heartbeat.h -- STATUS scheduling on the wrapping micros() clock.
//
// Owns: deciding when the next STATUS is due (at boot, then every period). Uses unsigned
// differences, so it is correct across the 2^32 us (71.6 min) wrap as long as the main loop
// runs at least once per 35 min. Does not build the STATUS frame (probe.cpp).
#ifndef STIPI_CORE_HEARTBEAT_H
#define STIPI_CORE_HEARTBEAT_H

#include <stdint.h>

namespace stipi {

class Heartbeat {
 public:
  explicit Heartbeat(uint32_t period_us) : period_us_(period_us), last_us_(0), started_(false) {}

  bool due(uint32_t now_us) const {
    return !started_ || static_cast<uint32_t>(now_us - last_us_) >= period_us_;
  }
  // Record a STATUS sent at now_us. Keeps the schedule (no drift) unless a whole period was
  // missed, in which case it restarts from now.
  void sent(uint32_t now_us) {
    if (started_ && static_cast<uint32_t>(now_us - last_us_) < 2 * period_us_) {
      last_us_ += period_us_;
    } else {
      last_us_ = now_us;
    }
    started_ = true;
  }
  uint32_t period_us() const { return period_us_; }

 private:
  uint32_t period_us_;
  uint32_t last_us_;
  bool started_;
};

}  // namespace stipi

#endif
