#include "behaviorlib/visual_markers/qr_finder.h"

#include <algorithm>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

namespace behaviorlib::markers {
namespace {

/// A line through `point` along the unit vector `direction`; `outward` is
/// its unit normal on the light side.
struct Line {
  cv::Point2f point;
  cv::Point2f direction;
  cv::Point2f outward;
};

float cross(const cv::Point2f& a, const cv::Point2f& b) { return a.x * b.y - a.y * b.x; }

std::optional<cv::Point2f> intersect(const Line& a, const Line& b) {
  const float denominator = cross(a.direction, b.direction);
  if (std::abs(denominator) < 1e-3f) return std::nullopt;  // (nearly) parallel
  const float t = cross(b.point - a.point, b.direction) / denominator;
  return a.point + t * a.direction;
}

/// `gray` (at least 2x2) at a sub-pixel point, bilinear, clamped at the
/// border.
float sample(const cv::Mat& gray, cv::Point2f p) {
  const float x = std::clamp(p.x, 0.0f, static_cast<float>(gray.cols - 1));
  const float y = std::clamp(p.y, 0.0f, static_cast<float>(gray.rows - 1));
  const int x0 = std::min(static_cast<int>(x), gray.cols - 2);
  const int y0 = std::min(static_cast<int>(y), gray.rows - 2);
  const float fx = x - static_cast<float>(x0), fy = y - static_cast<float>(y0);
  const auto at = [&](int r, int c) { return static_cast<float>(gray.at<uint8_t>(r, c)); };
  return (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) +
         fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1));
}

/// The edge between `from` and `to` (dark inside, light on the side of
/// `outward`) placed where the grey level crosses midway between the two,
/// across the middle of the edge: a sub-pixel line where the binary
/// contour's is quantised to whole pixels. `reach` (px) stays inside one
/// module. Keeps `line` when too few profiles have contrast.
void refineEdge(const cv::Mat& gray, cv::Point2f from, cv::Point2f to, float reach, Line& line) {
  const cv::Point2f along = to - from;
  const float length = static_cast<float>(cv::norm(along));
  if (length < 4) return;
  const cv::Point2f d = along / length;
  std::vector<cv::Point2f> crossings;
  constexpr float kStep = 0.25f;
  const int steps = static_cast<int>(2 * reach / kStep);
  std::vector<float> profile(static_cast<size_t>(steps) + 1);
  for (float t = 0.2f * length; t <= 0.8f * length; t += 1.0f) {
    const cv::Point2f base = from + t * d;
    float lo = 255, hi = 0;
    for (int i = 0; i <= steps; ++i) {
      profile[static_cast<size_t>(i)] = sample(gray, base + (-reach + kStep * i) * line.outward);
      lo = std::min(lo, profile[static_cast<size_t>(i)]);
      hi = std::max(hi, profile[static_cast<size_t>(i)]);
    }
    if (hi - lo < 24) continue;
    const float mid = 0.5f * (lo + hi);
    for (int i = 1; i <= steps; ++i) {
      const float a = profile[static_cast<size_t>(i - 1)], b = profile[static_cast<size_t>(i)];
      if (a < mid && b >= mid) {
        const float s = -reach + kStep * (static_cast<float>(i - 1) + (mid - a) / (b - a));
        crossings.push_back(base + s * line.outward);
        break;
      }
    }
  }
  if (crossings.size() < 4) return;
  cv::Vec4f fitted;
  cv::fitLine(crossings, fitted, cv::DIST_L2, 0, 0.01, 0.01);
  line.point = {fitted[2], fitted[3]};
  line.direction = {fitted[0], fitted[1]};
  const cv::Point2f normal(-fitted[1], fitted[0]);
  line.outward = normal.dot(line.outward) >= 0 ? normal : -normal;  // still the light side
}

/// One finder pattern: its outer square's edges and corners (sub-pixel).
struct Finder {
  cv::Point2f centre;
  /// edges[k] runs from corners[k] to corners[(k + 1) % 4].
  std::array<Line, 4> edges;
  std::array<cv::Point2f, 4> corners;
  float side = 0;
};

/// The outer square of a finder pattern from its contour (every boundary
/// pixel): four straight runs between the polygon's vertices, each fitted
/// with a line (its end pixels left out: they belong to the corners), moved
/// half a pixel outwards (the contour passes through the centres of the
/// boundary pixels, half a pixel inside the edge), intersected in turn.
std::optional<Finder> fitFinder(const cv::Mat& gray, const std::vector<cv::Point>& contour) {
  std::vector<cv::Point> polygon;
  cv::approxPolyDP(contour, polygon, 0.06 * cv::arcLength(contour, true), true);
  if (polygon.size() != 4 || !cv::isContourConvex(polygon)) return std::nullopt;
  // The vertices' places on the contour, in the contour's order.
  std::array<size_t, 4> at{};
  for (size_t k = 0; k < 4; ++k) {
    const auto it = std::find(contour.begin(), contour.end(), polygon[k]);
    if (it == contour.end()) return std::nullopt;
    at[k] = static_cast<size_t>(it - contour.begin());
  }
  std::sort(at.begin(), at.end());
  cv::Point2f centroid(0, 0);
  for (size_t k = 0; k < 4; ++k) {
    polygon[k] = contour[at[k]];
    centroid += cv::Point2f(polygon[k]) * 0.25f;
  }

  Finder finder;
  std::vector<cv::Point2f> run;
  const size_t n = contour.size();
  for (size_t k = 0; k < 4; ++k) {
    const size_t from = at[k], to = at[(k + 1) % 4];
    const size_t length = (to + n - from) % n;
    if (length < 2) return std::nullopt;
    const size_t trim = length >= 6 ? length / 6 : 0;
    run.clear();
    for (size_t i = trim; i <= length - trim; ++i) run.emplace_back(contour[(from + i) % n]);
    if (run.size() < 2) return std::nullopt;
    cv::Vec4f fitted;
    cv::fitLine(run, fitted, cv::DIST_L2, 0, 0.01, 0.01);
    Line line{{fitted[2], fitted[3]}, {fitted[0], fitted[1]}, {-fitted[1], fitted[0]}};
    if (line.outward.dot(line.point - centroid) < 0) line.outward = -line.outward;
    line.point += 0.5f * line.outward;
    finder.edges[k] = line;
  }
  const auto intersectEdges = [&finder]() {
    for (size_t k = 0; k < 4; ++k) {
      const auto corner = intersect(finder.edges[(k + 3) % 4], finder.edges[k]);
      if (!corner) return false;
      finder.corners[k] = *corner;
    }
    return true;
  };
  if (!intersectEdges()) return std::nullopt;
  // Then on the grey levels, within half a module of the edge.
  const float side_px = static_cast<float>(cv::norm(finder.corners[1] - finder.corners[0]) +
                                           cv::norm(finder.corners[3] - finder.corners[2])) /
                        2.0f;
  const float reach = std::clamp(0.45f * side_px / 7.0f, 1.0f, 3.0f);
  for (size_t k = 0; k < 4; ++k) {
    refineEdge(gray, finder.corners[k], finder.corners[(k + 1) % 4], reach, finder.edges[k]);
  }
  if (!intersectEdges()) return std::nullopt;
  finder.centre = cv::Point2f(0, 0);
  for (const auto& c : finder.corners) finder.centre += 0.25f * c;
  finder.side = static_cast<float>(std::sqrt(std::abs(cv::contourArea(finder.corners))));
  // A fit that moved a corner far from the polygon's is not a square's.
  for (size_t k = 0; k < 4; ++k) {
    if (cv::norm(finder.corners[k] - cv::Point2f(polygon[k])) > 0.25 * finder.side + 1.5) {
      return std::nullopt;
    }
  }
  return finder;
}

/// Finder patterns: a dark contour whose child (the light ring) has a child
/// (the dark centre) of about 9/49 of its area, all three concentric.
std::vector<Finder> findFinders(const cv::Mat& gray, const cv::Mat& binary) {
  std::vector<std::vector<cv::Point>> contours;
  std::vector<cv::Vec4i> hierarchy;
  cv::findContours(binary, contours, hierarchy, cv::RETR_TREE, cv::CHAIN_APPROX_NONE);
  std::vector<Finder> finders;
  for (size_t i = 0; i < contours.size(); ++i) {
    const int ring = hierarchy[i][2];
    if (ring < 0) continue;
    const int core = hierarchy[static_cast<size_t>(ring)][2];
    if (core < 0 || contours[i].size() < 24) continue;  // a side of at least ~6 px
    const double outer = cv::contourArea(contours[i]);
    const double inner = cv::contourArea(contours[static_cast<size_t>(ring)]);
    const double centre = std::max(1.0, cv::contourArea(contours[static_cast<size_t>(core)]));
    if (outer < 36 || outer / centre < 2.5 || outer / centre > 14 || inner / centre < 1.2 ||
        outer / inner < 1.2) {
      continue;
    }
    const cv::Moments mo = cv::moments(contours[i]);
    const cv::Moments mc = cv::moments(contours[static_cast<size_t>(core)]);
    if (mo.m00 <= 0 || mc.m00 <= 0) continue;
    const cv::Point2d co(mo.m10 / mo.m00, mo.m01 / mo.m00), cc(mc.m10 / mc.m00, mc.m01 / mc.m00);
    if (cv::norm(co - cc) > 0.2 * std::sqrt(outer)) continue;
    if (auto finder = fitFinder(gray, contours[i])) finders.push_back(*finder);
  }
  return finders;
}

struct Triple {
  size_t top_left, top_right, bottom_left;
  double score;
};

/// Width of `finder` along the unit direction `u` (px).
double extentAlong(const Finder& finder, const cv::Point2f& u) {
  double lo = 0, hi = 0;
  for (size_t k = 0; k < 4; ++k) {
    const double d = finder.corners[k].dot(u);
    lo = k == 0 ? d : std::min(lo, d);
    hi = k == 0 ? d : std::max(hi, d);
  }
  return hi - lo;
}

/// Three finders that can be one symbol's: similar sizes, a right angle at
/// the top-left one, equal legs, each at least two finder widths along it
/// (21 modules: the centres are 14 modules apart) and at most a version-40
/// symbol's 170 modules (~25 sides). Perspective bends all of it, hence the
/// tolerances (a code seen 60 degrees off its normal is foreshortened to
/// half its width; the finders' widths along a leg grow with the skew).
std::optional<Triple> asSymbol(const std::vector<Finder>& f, size_t a, size_t b, size_t c) {
  const float smallest = std::min({f[a].side, f[b].side, f[c].side});
  const float largest = std::max({f[a].side, f[b].side, f[c].side});
  if (largest > 1.8f * smallest) return std::nullopt;
  const double side = (f[a].side + f[b].side + f[c].side) / 3.0;
  std::optional<Triple> best;
  for (const auto& [v, p, q] : {std::array{a, b, c}, std::array{b, a, c}, std::array{c, a, b}}) {
    const cv::Point2f leg1 = f[p].centre - f[v].centre, leg2 = f[q].centre - f[v].centre;
    const double l1 = cv::norm(leg1), l2 = cv::norm(leg2);
    if (l1 < 1e-3 || l2 < 1e-3) continue;
    // Each leg against the finders' width along it (foreshortened alike).
    const double w1 = 0.5 * (extentAlong(f[v], leg1 / l1) + extentAlong(f[p], leg1 / l1));
    const double w2 = 0.5 * (extentAlong(f[v], leg2 / l2) + extentAlong(f[q], leg2 / l2));
    if (l1 < 1.35 * w1 || l2 < 1.35 * w2 || l1 > 26 * side || l2 > 26 * side) continue;
    const double ratio = l1 / l2;
    const double cosine = leg1.dot(leg2) / (l1 * l2);
    if (ratio < 0.45 || ratio > 1.0 / 0.45 || std::abs(cosine) > 0.55) continue;
    const double score = std::abs(std::log(ratio)) + std::abs(cosine) + (largest / smallest - 1.0);
    if (best && best->score <= score) continue;
    // Image y points down: the top-right finder is the first leg's when the
    // turn from it to the second is positive.
    best = cross(leg1, leg2) > 0 ? Triple{v, p, q, score} : Triple{v, q, p, score};
  }
  return best;
}

/// Index of the corner of `finder` farthest from `point`.
size_t farthestCorner(const Finder& finder, const cv::Point2f& point) {
  size_t best = 0;
  for (size_t k = 1; k < 4; ++k) {
    if (cv::norm(finder.corners[k] - point) > cv::norm(finder.corners[best] - point)) best = k;
  }
  return best;
}

/// The edge of `finder` at its corner `k` that leads away from `point`
/// (the symbol's outer edge towards the fourth corner).
const Line& edgeAwayFrom(const Finder& finder, size_t k, const cv::Point2f& point) {
  const size_t next = (k + 1) % 4, previous = (k + 3) % 4;
  return cv::norm(finder.corners[next] - point) > cv::norm(finder.corners[previous] - point)
             ? finder.edges[k]
             : finder.edges[previous];
}

/// The symbol's corners from all twelve finder corners: a homography from
/// the symbol's module grid (the version's size estimated from the finders
/// and rounded to 21 + 4k modules) fitted to them by least squares. The
/// fourth corner, which the two short finder edges reach only by a long
/// extrapolation, gets the support of the other nine points. Leaves `quad`
/// as it is when the fit does not agree with it.
void refineWithHomography(const Finder& tl, const Finder& tr, const Finder& bl, QrQuad& quad) {
  const auto& c = quad.corners;
  const double top = cv::norm(c[1] - c[0]) / (0.5 * (tl.side + tr.side));
  const double left = cv::norm(c[3] - c[0]) / (0.5 * (tl.side + bl.side));
  const double estimate = 3.5 * (top + left);  // 7 modules per finder side
  const int version = std::clamp(static_cast<int>(std::lround((estimate - 21.0) / 4.0)), 0, 39);
  const float n = static_cast<float>(21 + 4 * version);
  if (std::abs(estimate - n) > 1.5) return;  // between two sizes: trust neither

  const std::vector<cv::Point2f> square = {{0, 0}, {n, 0}, {n, n}, {0, n}};
  const cv::Matx33d to_modules =
      cv::getPerspectiveTransform(std::vector<cv::Point2f>(c.begin(), c.end()), square);
  std::vector<cv::Point2f> modules, pixels;
  for (const Finder* finder : {&tl, &tr, &bl}) {
    std::vector<cv::Point2f> mapped;
    cv::perspectiveTransform(
        std::vector<cv::Point2f>(finder->corners.begin(), finder->corners.end()), mapped,
        to_modules);
    for (size_t k = 0; k < 4; ++k) {
      // Finder corners lie on multiples of 7 from the symbol's edges.
      const auto snap = [n](float v) {
        const float from_start = std::round(v / 7.0f) * 7.0f;
        const float from_end = n - std::round((n - v) / 7.0f) * 7.0f;
        return std::abs(from_start - v) <= std::abs(from_end - v) ? from_start : from_end;
      };
      const cv::Point2f grid(snap(mapped[k].x), snap(mapped[k].y));
      if (cv::norm(grid - mapped[k]) > 1.5) return;
      modules.push_back(grid);
      pixels.push_back(finder->corners[k]);
    }
  }
  const cv::Mat fitted = cv::findHomography(modules, pixels, 0);
  if (fitted.empty()) return;
  std::vector<cv::Point2f> refined;
  cv::perspectiveTransform(square, refined, fitted);
  const double module_px = (tl.side + tr.side + bl.side) / 21.0;
  for (size_t k = 0; k < 4; ++k) {
    if (!std::isfinite(refined[k].x) || !std::isfinite(refined[k].y) ||
        cv::norm(refined[k] - c[k]) > 2.0 * module_px) {
      return;
    }
  }
  std::copy(refined.begin(), refined.end(), quad.corners.begin());
  quad.modules = static_cast<int>(n);
}

std::optional<QrQuad> toQuad(const std::vector<Finder>& f, const Triple& t) {
  const Finder &tl = f[t.top_left], &tr = f[t.top_right], &bl = f[t.bottom_left];
  const cv::Point2f middle = 0.5f * (tr.centre + bl.centre);
  const size_t tl_k = farthestCorner(tl, middle), tr_k = farthestCorner(tr, middle),
               bl_k = farthestCorner(bl, middle);
  const auto br = intersect(edgeAwayFrom(tr, tr_k, tl.centre), edgeAwayFrom(bl, bl_k, tl.centre));
  if (!br) return std::nullopt;
  QrQuad quad;
  quad.corners = {tl.corners[tl_k], tr.corners[tr_k], *br, bl.corners[bl_k]};
  quad.finder_side_px = (tl.side + tr.side + bl.side) / 3.0f;
  // The fourth corner must close a convex quadrilateral not much larger than
  // the three finders' span (near-parallel edges put it far away).
  if (!cv::isContourConvex(std::vector<cv::Point2f>(quad.corners.begin(), quad.corners.end()))) {
    return std::nullopt;
  }
  const double diagonal = cv::norm(quad.corners[1] - quad.corners[3]);
  if (cv::norm(*br - quad.corners[0]) > 2.0 * diagonal) return std::nullopt;
  refineWithHomography(tl, tr, bl, quad);
  return quad;
}

}  // namespace

std::vector<QrQuad> findQrSymbols(const cv::Mat& gray) {
  std::vector<QrQuad> symbols;
  if (gray.type() != CV_8UC1 || gray.cols < 16 || gray.rows < 16) return symbols;
  // Dark = 255. A local mean over a window larger than a near code's 3x3
  // centre keeps the centre dark; the offset keeps flat surfaces light.
  const int block = std::max(15, (std::min(gray.cols, gray.rows) / 8) | 1);
  cv::Mat binary;
  cv::adaptiveThreshold(gray, binary, 255, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, block,
                        8);
  const std::vector<Finder> finders = findFinders(gray, binary);

  // Every triple is scored; the best ones that share no finder are symbols
  // (the first 48 finders: 17 296 triples at most).
  std::vector<Triple> triples;
  const size_t n = std::min<size_t>(finders.size(), 48);
  for (size_t a = 0; a < n; ++a) {
    for (size_t b = a + 1; b < n; ++b) {
      for (size_t c = b + 1; c < n; ++c) {
        if (auto triple = asSymbol(finders, a, b, c)) triples.push_back(*triple);
      }
    }
  }
  std::sort(triples.begin(), triples.end(),
            [](const Triple& x, const Triple& y) { return x.score < y.score; });
  std::vector<bool> used(n, false);
  for (const Triple& t : triples) {
    if (used[t.top_left] || used[t.top_right] || used[t.bottom_left]) continue;
    if (auto quad = toQuad(finders, t)) {
      used[t.top_left] = used[t.top_right] = used[t.bottom_left] = true;
      symbols.push_back(*quad);
    }
  }
  return symbols;
}

}  // namespace behaviorlib::markers
