// When is a system down: stream broken and health failing for the grace
// period, declared once per outage. Time is given explicitly (fake).

#include "coordinator/registry/supervision.h"

#include <gtest/gtest.h>

namespace behaviorlib::coordinator {
namespace {

using std::chrono::milliseconds;

class SupervisionTest : public ::testing::Test {
 protected:
  Supervision::TimePoint at(int ms) const { return t0_ + milliseconds(ms); }

  const Supervision::TimePoint t0_ = Supervision::TimePoint(std::chrono::hours(1));
  Supervision supervision_{milliseconds(1000)};
};

TEST_F(SupervisionTest, DownOnlyAfterHealthFailedForTheWholeGracePeriod) {
  supervision_.streamUp();
  supervision_.streamBroken(at(0));
  EXPECT_FALSE(supervision_.healthChecked(false, at(10)));
  EXPECT_EQ(supervision_.failingSince(), at(10));
  EXPECT_FALSE(supervision_.healthChecked(false, at(500)));
  EXPECT_FALSE(supervision_.healthChecked(false, at(1009)));
  EXPECT_TRUE(supervision_.healthChecked(false, at(1010)));
  EXPECT_TRUE(supervision_.down());
  EXPECT_FALSE(supervision_.healthChecked(false, at(2000))) << "declared once per outage";
  EXPECT_TRUE(supervision_.down());
}

TEST_F(SupervisionTest, AnAnsweringHealthCheckRestartsTheGracePeriod) {
  supervision_.streamBroken(at(0));
  EXPECT_FALSE(supervision_.healthChecked(false, at(0)));
  EXPECT_FALSE(supervision_.healthChecked(true, at(900)));
  EXPECT_FALSE(supervision_.failingSince().has_value());
  EXPECT_FALSE(supervision_.healthChecked(false, at(1200)));
  EXPECT_FALSE(supervision_.healthChecked(false, at(2100)));
  EXPECT_TRUE(supervision_.healthChecked(false, at(2200)));
}

TEST_F(SupervisionTest, HealthIsIgnoredWhileTheStreamIsUp) {
  supervision_.streamUp();
  EXPECT_FALSE(supervision_.healthChecked(false, at(0)));
  EXPECT_FALSE(supervision_.healthChecked(false, at(5000)));
  EXPECT_FALSE(supervision_.down());
}

TEST_F(SupervisionTest, ReconnectingEndsTheOutageAndALaterOneIsDeclaredAgain) {
  supervision_.streamBroken(at(0));
  supervision_.healthChecked(false, at(0));
  ASSERT_TRUE(supervision_.healthChecked(false, at(1000)));
  supervision_.streamUp();
  EXPECT_FALSE(supervision_.down());
  EXPECT_FALSE(supervision_.failingSince().has_value());
  supervision_.streamBroken(at(5000));
  EXPECT_FALSE(supervision_.healthChecked(false, at(5000)));
  EXPECT_TRUE(supervision_.healthChecked(false, at(6000)));
}

TEST_F(SupervisionTest, AFrozenSystemIsUnansweredAfterTheGraceAndDownAtTheBreak) {
  // The stream stays open (a SIGSTOPped process) while probes fail.
  supervision_.streamUp();
  EXPECT_FALSE(supervision_.healthChecked(false, at(100)));
  EXPECT_EQ(supervision_.failingSince(), at(100));
  EXPECT_FALSE(supervision_.unanswered(at(1099)));
  EXPECT_FALSE(supervision_.healthChecked(false, at(1099)));
  EXPECT_TRUE(supervision_.unanswered(at(1100)));
  EXPECT_FALSE(supervision_.down()) << "not down while the stream is up";
  // The link breaks the stream: the failing window is kept, so the next
  // failed check declares it down at once.
  supervision_.streamBroken(at(1150));
  EXPECT_FALSE(supervision_.unanswered(at(1150)));
  EXPECT_TRUE(supervision_.healthChecked(false, at(1160)));
  EXPECT_TRUE(supervision_.down());
}

TEST_F(SupervisionTest, AnAnswerWhileTheStreamIsUpRestartsTheWindow) {
  supervision_.streamUp();
  supervision_.healthChecked(false, at(0));
  supervision_.healthChecked(true, at(900));
  EXPECT_FALSE(supervision_.failingSince().has_value());
  supervision_.healthChecked(false, at(1000));
  EXPECT_FALSE(supervision_.unanswered(at(1500)));
  EXPECT_TRUE(supervision_.unanswered(at(2000)));
  supervision_.streamUp();  // a new stream: the outage is over
  EXPECT_FALSE(supervision_.unanswered(at(5000)));
}

}  // namespace
}  // namespace behaviorlib::coordinator
