// Layered mass-spring-damper skin (see tpscore/skin_sim.hpp).
#include "tpscore/skin_sim.hpp"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <utility>

#include "tpscore/closest_point.hpp"
#include "tpscore/parallel.hpp"

namespace tpscore {

namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;

// Below this many particles a loop runs on the calling thread. A semi-implicit step
// of the template (7,700 particles, 65,000 springs) takes about 2 ms on one core, in
// a few passes (springs, particles, contact): 2048 particles are about half a
// millisecond of a step's work, against a hand-off to the pool of microseconds (tens
// when its threads have gone to sleep between calls; see parallel.cpp).
constexpr std::size_t kMinChunk = 2048;

// A pivot of D below this fraction of the largest means the implicit system lost
// positive definiteness (it cannot, by construction; this is a guard).
constexpr double kPivotTolerance = 1e-14;

// Length (mm) over which a muscle's pull fades to zero at its attachment (see forces).
constexpr double kMuscleCore = 1.0;

// The contact direction blends triangles up to this fraction of the largest contact
// margin farther than the closest one (see blended_direction).
constexpr double kContactBlend = 0.5;
// Width of the rounded lip the skull's rim ends in, in largest contact margins (see
// lip_contact): 4 mm at the default 0.5 mm margin.
constexpr double kRimRounding = 8.0;


// One spring seen from its first particle: unit direction toward the second, current
// length, elastic force along the direction (positive = tension) and its slope dF/dl.
struct SpringState {
    Vec3 direction = Vec3::Zero();
    double length = 0.0;
    double force = 0.0;
    double slope = 0.0;
};

// The biphasic law: slope k up to the knee extension knee * l0, slope k_high beyond,
// symmetric in compression.
inline double biphasic_force(double extension, double rest, double k, double k_high,
                             double knee, double* slope) {
    const double limit = knee * rest;
    const double magnitude = std::abs(extension);
    if (magnitude <= limit) {
        *slope = k;
        return k * extension;
    }
    *slope = k_high;
    const double force = k * limit + k_high * (magnitude - limit);
    return extension >= 0.0 ? force : -force;
}

inline double biphasic_energy(double extension, double rest, double k, double k_high,
                              double knee) {
    const double limit = knee * rest;
    const double magnitude = std::abs(extension);
    if (magnitude <= limit) return 0.5 * k * extension * extension;
    const double beyond = magnitude - limit;
    return 0.5 * k * limit * limit + k * limit * beyond + 0.5 * k_high * beyond * beyond;
}

inline Vec3 row(const Points& points, std::int64_t i) {
    return points.row(static_cast<Eigen::Index>(i)).transpose();
}

inline Vec3 row(const PointsRef& points, std::int64_t i) {
    return points.row(static_cast<Eigen::Index>(i)).transpose();
}

inline double smoothstep(double s) {
    s = std::clamp(s, 0.0, 1.0);
    return s * s * (3.0 - 2.0 * s);
}

}  // namespace

namespace {

// A prism's volume and its gradient with respect to its six corners (rows): three
// tetrahedra (a b c A), (b c A B), (c A B C) of the corners a b c over A B C.
struct PrismVolume {
    double volume = 0.0;
    Eigen::Matrix<double, 6, 3> gradient = Eigen::Matrix<double, 6, 3>::Zero();
};

inline void add_tetrahedron(const Vec3 (&x)[6], int i0, int i1, int i2, int i3, PrismVolume& out) {
    const Vec3 e1 = x[i1] - x[i0], e2 = x[i2] - x[i0], e3 = x[i3] - x[i0];
    const Vec3 g1 = e2.cross(e3) / 6.0, g2 = e3.cross(e1) / 6.0, g3 = e1.cross(e2) / 6.0;
    out.volume += e1.dot(g1);
    out.gradient.row(i1) += g1.transpose();
    out.gradient.row(i2) += g2.transpose();
    out.gradient.row(i3) += g3.transpose();
    out.gradient.row(i0) -= (g1 + g2 + g3).transpose();
}

template <class P>
inline PrismVolume prism_volume(const SkinSystemData& d, const P& positions, std::int64_t prism) {
    Vec3 x[6];
    for (int c = 0; c < 6; ++c) x[c] = positions.row(d.prism_particles(prism, c)).transpose();
    PrismVolume out;
    add_tetrahedron(x, 0, 1, 2, 3, out);
    add_tetrahedron(x, 1, 2, 3, 4, out);
    add_tetrahedron(x, 2, 3, 4, 5, out);
    return out;
}

}  // namespace

namespace {

// Items 0..items-1 grouped by the particle each belongs to (particle_of(item)), in item
// order within each particle: CSR offsets (n + 1) and the grouped items.
template <class ParticleOf>
void group_by_particle(std::int64_t n, std::int64_t items, ParticleOf particle_of,
                       std::vector<std::int64_t>& offsets, std::vector<std::int64_t>& grouped) {
    offsets.assign(static_cast<std::size_t>(n) + 1, 0);
    for (std::int64_t e = 0; e < items; ++e) ++offsets[static_cast<std::size_t>(particle_of(e)) + 1];
    for (std::int64_t i = 0; i < n; ++i) offsets[i + 1] += offsets[i];
    grouped.resize(static_cast<std::size_t>(items));
    std::vector<std::int64_t> fill(offsets.begin(), offsets.end() - 1);
    for (std::int64_t e = 0; e < items; ++e) grouped[static_cast<std::size_t>(fill[particle_of(e)]++)] = e;
}

// One triangle near a particle's skull vertex: the particle's closest point on it.
struct SkullHit {
    std::int64_t face;
    Vec3 point;
    double squared_distance;
    bool on_rim;  // the closest point lies on a rim edge of the bone
    Vec3 barycentric;
};

// The weight of a triangle `excess` farther than the closest one in the blends over the
// nearly-as-close triangles: 1 for the closest, (1 - excess / blend)^2 within `blend`,
// 0 (left out) beyond.
inline double closeness_weight(bool nearest, double excess, double blend) {
    if (nearest) return 1.0;
    if (!(excess < blend)) return 0.0;
    return (1.0 - excess / blend) * (1.0 - excess / blend);
}

// The direction out of the skull at a particle outside it (or beside its rim), blended
// over the triangles whose distance is within `blend` of the closest one's (hit
// `closest`, at `distance`), each weighted (1 - excess / blend)^2: in a concave crease
// the closest point jumps from one side to the other as a particle crosses the
// crease's middle, and with it the direction of the penalty; a particle held in the
// crease then chattered from side to side and never came to rest. Blended, the
// direction turns continuously, and triangles that share the closest point (an edge,
// a corner) give the same direction and change nothing.
Vec3 blended_direction(const Vec3& x, const std::vector<SkullHit>& hits, std::size_t closest,
                       double distance, double blend, const Points& face_normals) {
    const std::int64_t face = hits[closest].face;
    if (!(distance > 1e-12)) return row(face_normals, face);
    Vec3 sum = Vec3::Zero();
    for (std::size_t h = 0; h < hits.size(); ++h) {
        const SkullHit& hit = hits[h];
        const double own = std::sqrt(hit.squared_distance);
        const bool nearest = h == closest;
        const double w = closeness_weight(nearest, own - distance, blend);
        if (w == 0.0) continue;
        if (!(own > 1e-12)) continue;
        const Vec3 offset = x - hit.point;
        // a triangle the particle lies behind (and not beside its rim) has no say
        if (!nearest && !hit.on_rim && offset.dot(row(face_normals, hit.face)) < 0.0) continue;
        sum += w * offset / own;
    }
    const double length = sum.norm();
    return length > 1e-12 ? Vec3(sum / length) : Vec3(row(face_normals, face));
}

// The skull's rim ends in a rounded lip `rounding` wide that curves back behind the
// rim by as much. For a particle whose closest point on a triangle (`hit`) lies on a
// rim edge, within `rounding` of that edge across it: the height over the lip and its
// direction (the unit gradient), and how far across the edge the particle lies. The
// height is measured along a normal that turns from the triangle's (at the edge, where
// the height meets that of a particle over or behind the triangle) to the rim's own
// vertex normals, interpolated along the edge (which agree from one rim triangle to
// the next), raised by the lip's curve and divided by its gradient's length (the
// distance to the lip's surface to first order: the level itself rises up to 1.8
// times faster across the lip, and the penalty would be that much stiffer than the
// stable step allows for). Counting a particle beyond the edge as beside it instead,
// at its distance from it, let tissue slip round the edge to the bone's back; there,
// one step past the edge it counted as inside and was thrown back to the front, and a
// particle that orbited the edge so never came to rest. Returns false beyond the lip.
bool lip_contact(const Vec3& x, const SkullHit& hit, double rounding, const Points& face_normals,
                 const Points& vertex_normals, const Faces& faces, double& height, Vec3& direction,
                 double& across) {
    const Vec3 face_normal = row(face_normals, hit.face);
    const Vec3 offset = x - hit.point;
    const Vec3 beyond = offset - offset.dot(face_normal) * face_normal;
    across = beyond.norm();
    if (!(across < rounding)) return false;
    Vec3 rim_normal = Vec3::Zero();
    for (int k = 0; k < 3; ++k) rim_normal += hit.barycentric[k] * row(vertex_normals, faces(hit.face, k));
    rim_normal.normalize();
    const double s = across / rounding;
    const double curve = s * s * (3.0 - 2.0 * s);  // 0 at the edge, 1 at the lip's end, flat at both
    const double rise = 6.0 * s * (1.0 - s);        // its slope across
    const Vec3 outward = across > 1e-12 ? Vec3(beyond / across) : Vec3::Zero();
    const Vec3 normal = ((1.0 - curve) * face_normal + curve * rim_normal).normalized();
    const Vec3 gradient = normal + rise * outward;
    const double slope = gradient.norm();
    height = (offset.dot(normal) + rounding * curve) / slope;
    direction = gradient / slope;
    return true;
}

// Contact where the closest point (hit `closest`, at `distance`) lies on the skull's
// rim: height and direction averaged over the rim triangles nearly as close
// (closeness_weight), each giving its lip's height and direction
// (lip_contact), or beyond the lip its distance and the direction away from it. Where
// two rims meet (the outline and the seam to the other bone, a corner of the
// outline) the closest triangle switches from one rim to the other, and each alone
// gives another height and direction: a particle there once flicked between the two
// at every step. Within `blend` of the edge the direction is handed over from the one
// a particle just over the closest triangle gets (blended_direction over every
// nearly-as-close triangle, or straight out from behind): a particle resting on the
// edge flicked between those two as well. Farther out the other triangles are left
// out of the direction: a particle level with the rim lies in the plane of its
// neighbours, whose say switched on and off as it crossed them. At the edge, one rim
// triangle alone gives the height over it, which meets the height over the triangle.
SkullContact rim_contact(const Vec3& x, const std::vector<SkullHit>& hits, std::size_t closest,
                         double distance, double blend, double rounding, const Points& face_normals,
                         const Points& vertex_normals, const Faces& faces) {
    SkullContact contact;
    contact.face = hits[closest].face;
    Vec3 rim_sum = Vec3::Zero();
    double height_sum = 0.0, weight_sum = 0.0, across = 0.0;
    for (std::size_t h = 0; h < hits.size(); ++h) {
        const SkullHit& hit = hits[h];
        if (!hit.on_rim) continue;
        const double own = std::sqrt(hit.squared_distance);
        const bool nearest = h == closest;
        const double w = closeness_weight(nearest, own - distance, blend);
        if (w == 0.0) continue;
        double height = own, hit_across = 0.0;
        Vec3 direction = own > 1e-12 ? Vec3((x - hit.point) / own) : Vec3(row(face_normals, hit.face));
        lip_contact(x, hit, rounding, face_normals, vertex_normals, faces, height, direction, hit_across);
        if (nearest) across = hit_across;
        height_sum += w * height;
        weight_sum += w;
        rim_sum += w * direction;
    }
    contact.height = height_sum / weight_sum;  // the closest hit is on the rim: weight_sum >= 1
    const double length = rim_sum.norm();
    Vec3 normal = length > 1e-12 ? Vec3(rim_sum / length) : Vec3(row(face_normals, contact.face));
    const double t = blend > 0.0 ? std::min(across / blend, 1.0) : 1.0;
    if (t < 1.0) {
        const double handover = t * t * (3.0 - 2.0 * t);
        const Vec3 face_normal = row(face_normals, contact.face);
        // just over the triangle: blended in front, straight out from behind
        const Vec3 edge = (x - hits[closest].point).dot(face_normal) < 0.0
                              ? face_normal
                              : blended_direction(x, hits, closest, distance, blend, face_normals);
        normal = ((1.0 - handover) * edge + handover * normal).normalized();
    }
    contact.normal = normal;
    contact.point = x - contact.height * contact.normal;
    return contact;
}

}  // namespace

JawMotion::JawMotion(const Eigen::Vector3d& pivot_point, const Eigen::Vector3d& axis,
                     double angle)
    : rotation(Eigen::AngleAxisd(angle, axis).toRotationMatrix()), pivot(pivot_point) {}

Eigen::Vector3d JawMotion::apply(const Eigen::Vector3d& point, std::int64_t bone) const {
    if (bone != kMandible) return point;
    return pivot + rotation * (point - pivot);
}

SkullContact SkinSystem::locate(const Eigen::Vector3d& x, std::int64_t foot,
                                const SkullGeometry& skull) const {
    // The closest point of the triangles near the nearest skull vertex (its two-ring):
    // among those wholly on that vertex's bone: the skull's own surface, so the height
    // and its direction change continuously as a particle slides (a vertex's tangent
    // plane jumps from one vertex to the next, and so would the closest point of its
    // one-ring alone where the true closest point lies one ring farther; a penalty
    // along a jumping surface pumps energy into the tissue). The triangles across the
    // seam between skull and mandible belong to neither: the open jaw pulls them apart.
    const SkinSystemData& d = data_;
    SkullContact best;
    // Far above the vertex's tangent plane, the triangles near it (which rise at most
    // skull_rise above it) are farther than the contact margin: no need to look closer.
    best.normal = row(skull.normals, foot);
    best.height = (x - row(skull.vertices, foot)).dot(best.normal);
    if (best.height > max_margin_ + skull_rise_[static_cast<std::size_t>(foot)]) {
        best.point = x - best.height * best.normal;
        return best;
    }
    // Every triangle near the vertex wholly on its bone, with the particle's closest
    // point on it, found once: the closest one gives the height, the nearly-as-close
    // ones the direction (blended_direction). The buffer is the calling thread's own.
    thread_local std::vector<SkullHit> hits;
    hits.clear();
    const std::int64_t bone = d.skull_bone[foot];
    std::size_t closest = 0;
    for (std::int64_t e = d.skull_face_indptr[foot]; e < d.skull_face_indptr[foot + 1]; ++e) {
        const std::int64_t f = d.skull_vertex_faces[e];
        const std::int64_t a = d.skull_faces(f, 0), b = d.skull_faces(f, 1), c = d.skull_faces(f, 2);
        if (d.skull_bone[a] != bone || d.skull_bone[b] != bone || d.skull_bone[c] != bone) continue;
        const Vec3 pa = row(skull.vertices, a), pb = row(skull.vertices, b), pc = row(skull.vertices, c);
        const TrianglePoint t = closest_point_on_triangle(x.data(), pa.data(), pb.data(), pc.data());
        // on the rim: an edge opposite a corner whose weight is zero is a rim edge
        bool on_rim = false;
        for (int k = 0; k < 3; ++k)
            if (t.barycentric[k] == 0.0 && (d.skull_face_rim[f] >> k) & 1) on_rim = true;
        hits.push_back({f, Vec3(t.point[0], t.point[1], t.point[2]), t.squared_distance, on_rim,
                        Vec3(t.barycentric[0], t.barycentric[1], t.barycentric[2])});
        if (t.squared_distance < hits[closest].squared_distance) closest = hits.size() - 1;
    }
    if (hits.empty()) {
        // no triangle wholly on the bone (at the jaw's seam): the vertex's tangent plane
        best.point = x - best.height * best.normal;
        return best;
    }
    const SkullHit& nearest = hits[closest];
    best.face = nearest.face;
    best.point = nearest.point;
    const double distance = std::sqrt(nearest.squared_distance);
    const double blend = kContactBlend * max_margin_;
    if (nearest.on_rim)
        // the closest skull point lies on the rim of the particle's bone (the skull's
        // outline, the seam to the other bone)
        return rim_contact(x, hits, closest, distance, blend, kRimRounding * max_margin_, skull.face_normals,
                           skull.normals, d.skull_faces);
    const Vec3 face_normal = row(skull.face_normals, best.face);
    const Vec3 offset = x - best.point;
    if (offset.dot(face_normal) < 0.0) {
        // inside the skull: straight back out of the closest triangle (the projection
        // moves the particle there)
        best.height = -distance;
        best.normal = distance > 1e-12 ? Vec3(-offset / distance) : face_normal;
        return best;
    }
    best.height = distance;
    best.normal = blended_direction(x, hits, closest, distance, blend, skull.face_normals);
    return best;
}

SkinSystem::SkinSystem(SkinSystemData data) : data_(std::move(data)) {
    const std::int64_t n = particles();
    const std::int64_t springs = static_cast<std::int64_t>(data_.spring_first.size());
    const std::int64_t anchors = static_cast<std::int64_t>(data_.anchor_particle.size());

    // Per-particle incidence lists (CSR), each in its items' order: a particle's forces
    // are always summed in the same order.
    std::vector<std::int64_t> ends;  // spring item 2 s + side: the particle at that end
    group_by_particle(n, 2 * springs, [&](std::int64_t e) {
        return e % 2 == 0 ? data_.spring_first[e / 2] : data_.spring_second[e / 2];
    }, spring_offsets_, ends);
    spring_incidence_.resize(ends.size());
    for (std::size_t slot = 0; slot < ends.size(); ++slot) {
        const std::int64_t s = ends[slot] / 2;
        spring_incidence_[slot] = {s, ends[slot] % 2 == 0 ? data_.spring_second[s] : data_.spring_first[s]};
    }

    group_by_particle(n, anchors, [&](std::int64_t a) { return data_.anchor_particle[a]; }, anchor_offsets_,
                      anchor_index_);

    const std::int64_t k = muscles();
    const std::int64_t entries = data_.muscle_indptr.size() ? data_.muscle_indptr[k] : 0;
    std::vector<std::int64_t> muscle_entry;
    group_by_particle(n, entries, [&](std::int64_t e) { return data_.muscle_particles[e]; }, muscle_offsets_,
                      muscle_entry);
    std::vector<std::int64_t> muscle_of(static_cast<std::size_t>(entries));
    for (std::int64_t m = 0; m < k; ++m)
        for (std::int64_t e = data_.muscle_indptr[m]; e < data_.muscle_indptr[m + 1]; ++e)
            muscle_of[static_cast<std::size_t>(e)] = m;
    muscle_of_entry_.resize(muscle_entry.size());
    weight_of_entry_.resize(muscle_entry.size());
    for (std::size_t slot = 0; slot < muscle_entry.size(); ++slot) {
        muscle_of_entry_[slot] = muscle_of[static_cast<std::size_t>(muscle_entry[slot])];
        weight_of_entry_[slot] = data_.muscle_weights[muscle_entry[slot]];
    }

    const std::int64_t prisms = static_cast<std::int64_t>(data_.prism_particles.rows());
    group_by_particle(n, 6 * prisms, [&](std::int64_t e) { return data_.prism_particles(e / 6, e % 6); },
                      prism_offsets_, prism_corner_);

    data_.rest_stiffness = VectorX::Zero(n);
    for (std::int64_t s = 0; s < springs; ++s) {
        data_.rest_stiffness[data_.spring_first[s]] += data_.spring_stiffness[s];
        data_.rest_stiffness[data_.spring_second[s]] += data_.spring_stiffness[s];
    }
    for (std::int64_t a = 0; a < anchors; ++a)
        data_.rest_stiffness[data_.anchor_particle[a]] += data_.anchor_stiffness[a];
    // (The prisms' volume stiffness is left out: the system does not know the rest
    // positions its gradients need, and a smaller scale only makes the test stricter.)
    for (std::int64_t i = 0; i < n; ++i)
        if (!(data_.rest_stiffness[i] > 0.0)) data_.rest_stiffness[i] = 1.0;  // a free particle

    max_margin_ = data_.contact_margin.size() ? data_.contact_margin.maxCoeff() : 0.0;
    // How far the triangles listed for each skull vertex (those on its own bone, the
    // only ones the contact search uses) rise above its tangent plane: a particle
    // higher than that plus the contact margin cannot touch them. They move rigidly
    // with their bone, so this holds at any jaw angle.
    skull_rise_.assign(static_cast<std::size_t>(data_.skull_vertices.rows()), 0.0);
    for (Eigen::Index v = 0; v < data_.skull_vertices.rows(); ++v) {
        const Vec3 origin = row(data_.skull_vertices, v);
        const Vec3 normal = row(data_.skull_normals, v);
        for (std::int64_t e = data_.skull_face_indptr[v]; e < data_.skull_face_indptr[v + 1]; ++e)
            for (int k = 0; k < 3; ++k) {
                const std::int64_t corner = data_.skull_faces(data_.skull_vertex_faces[e], k);
                if (data_.skull_bone[corner] != data_.skull_bone[v]) continue;
                const double rise = (row(data_.skull_vertices, corner) - origin).dot(normal);
                skull_rise_[static_cast<std::size_t>(v)] = std::max(skull_rise_[static_cast<std::size_t>(v)], rise);
            }
    }
    build_pattern();
}

void SkinSystem::build_pattern() {
    const std::int64_t n = particles();
    const std::int64_t springs = static_cast<std::int64_t>(data_.spring_first.size());
    // Higher-indexed neighbours of each particle, sorted and unique: the off-diagonal
    // blocks of its block column.
    std::vector<std::vector<std::int64_t>> higher(static_cast<std::size_t>(n));
    for (std::int64_t s = 0; s < springs; ++s) {
        const std::int64_t a = data_.spring_first[s], b = data_.spring_second[s];
        higher[static_cast<std::size_t>(std::min(a, b))].push_back(std::max(a, b));
    }
    const std::int64_t prisms = static_cast<std::int64_t>(data_.prism_particles.rows());
    for (std::int64_t q = 0; q < prisms; ++q)
        for (int c = 0; c < 6; ++c)
            for (int r = c + 1; r < 6; ++r) {
                const std::int64_t a = data_.prism_particles(q, c), b = data_.prism_particles(q, r);
                higher[static_cast<std::size_t>(std::min(a, b))].push_back(std::max(a, b));
            }
    for (auto& list : higher) {
        std::sort(list.begin(), list.end());
        list.erase(std::unique(list.begin(), list.end()), list.end());
    }
    pattern_indptr_.assign(static_cast<std::size_t>(3 * n) + 1, 0);
    for (std::int64_t j = 0; j < n; ++j) {
        const std::int64_t off = 3 * static_cast<std::int64_t>(higher[j].size());
        for (std::int64_t c = 0; c < 3; ++c)
            pattern_indptr_[3 * j + c + 1] = pattern_indptr_[3 * j + c] + (3 - c) + off;
    }
    pattern_indices_.resize(static_cast<std::size_t>(pattern_indptr_.back()));
    for (std::int64_t j = 0; j < n; ++j) {
        for (std::int64_t c = 0; c < 3; ++c) {
            std::int64_t at = pattern_indptr_[3 * j + c];
            for (std::int64_t r = c; r < 3; ++r) pattern_indices_[at++] = 3 * j + r;
            for (std::int64_t i : higher[j])
                for (std::int64_t r = 0; r < 3; ++r) pattern_indices_[at++] = 3 * i + r;
        }
    }
    spring_block_.resize(static_cast<std::size_t>(springs));
    for (std::int64_t s = 0; s < springs; ++s) {
        const std::int64_t a = data_.spring_first[s], b = data_.spring_second[s];
        const auto& list = higher[static_cast<std::size_t>(std::min(a, b))];
        spring_block_[s] =
            std::lower_bound(list.begin(), list.end(), std::max(a, b)) - list.begin();
    }
    prism_block_.assign(static_cast<std::size_t>(36 * prisms), -1);
    for (std::int64_t q = 0; q < prisms; ++q)
        for (int c = 0; c < 6; ++c)
            for (int r = 0; r < 6; ++r) {
                const std::int64_t column = data_.prism_particles(q, c), other = data_.prism_particles(q, r);
                if (other <= column) continue;
                const auto& list = higher[static_cast<std::size_t>(column)];
                prism_block_[static_cast<std::size_t>(36 * q + 6 * c + r)] =
                    std::lower_bound(list.begin(), list.end(), other) - list.begin();
            }
    // The ordering and symbolic analysis happen on the first implicit step: a system
    // that only ever steps semi-implicitly never pays for them.
}

Points SkinSystem::bone_points(const Points& points, const IndexVector& bones,
                               const JawMotion& jaw) const {
    Points moved(points.rows(), 3);
    for (Eigen::Index i = 0; i < points.rows(); ++i)
        moved.row(i) = jaw.apply(points.row(i).transpose(), bones[i]).transpose();
    return moved;
}

Points SkinSystem::muscle_points(const JawMotion& jaw) const {
    return bone_points(data_.muscle_point, data_.muscle_bone, jaw);
}

namespace {

inline SpringState evaluate_spring(const SkinSystemData& d, std::int64_t s, const Vec3& from,
                                   const Vec3& to) {
    SpringState state;
    const Vec3 delta = to - from;
    state.length = delta.norm();
    if (state.length > 0.0) state.direction = delta / state.length;
    state.force = biphasic_force(state.length - d.spring_rest[s], d.spring_rest[s],
                                 d.spring_stiffness[s], d.spring_stiffness_high[s],
                                 d.spring_knee[s], &state.slope);
    return state;
}

}  // namespace

void SkinSystem::accumulate_forces(const SkinState& state, const SkinControls& controls,
                                   const Points& anchors, const Points& attachments,
                                   const SkullGeometry& skull, Points& out) const {
    const std::int64_t n = particles();
    const SkinSystemData& d = data_;
    out.resize(n, 3);
    // Each spring's force once (on its first particle; the second gets the opposite),
    // then each particle gathers its springs in a fixed order: no two threads write one
    // row, and the sums do not depend on how the loops are split.
    const std::int64_t springs = static_cast<std::int64_t>(d.spring_first.size());
    Points spring_force(springs, 3);
    parallel_for(static_cast<std::size_t>(springs), 4 * kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t q = begin; q < end; ++q) {
            const std::int64_t k = static_cast<std::int64_t>(q);
            const std::int64_t a = d.spring_first[k], b = d.spring_second[k];
            const SpringState s = evaluate_spring(d, k, row(state.positions, a), row(state.positions, b));
            const double damping = d.spring_damping[k] *
                                   s.direction.dot(row(state.velocities, b) - row(state.velocities, a));
            spring_force.row(k) = ((s.force + damping) * s.direction).transpose();
        }
    });
    // Each prism's volume force on its six corners, gathered the same way.
    const std::int64_t prisms = static_cast<std::int64_t>(d.prism_particles.rows());
    Points corner_force(6 * prisms, 3);
    parallel_for(static_cast<std::size_t>(prisms), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t q = begin; q < end; ++q) {
            const std::int64_t k = static_cast<std::int64_t>(q);
            const PrismVolume prism = prism_volume(d, state.positions, k);
            const double pressure = -d.prism_stiffness[k] * (prism.volume - d.prism_rest_volume[k]);
            corner_force.middleRows<6>(6 * k) = pressure * prism.gradient;
        }
    });
    parallel_for(static_cast<std::size_t>(n), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            const std::int64_t i = static_cast<std::int64_t>(p);
            const Vec3 x = row(state.positions, i);
            const Vec3 v = row(state.velocities, i);
            Vec3 total = -d.drag * d.masses[i] * v;
            for (std::int64_t e = prism_offsets_[p]; e < prism_offsets_[p + 1]; ++e)
                total += row(corner_force, prism_corner_[static_cast<std::size_t>(e)]);
            for (std::int64_t e = spring_offsets_[p]; e < spring_offsets_[p + 1]; ++e) {
                const Incidence& inc = spring_incidence_[static_cast<std::size_t>(e)];
                const Vec3 f = row(spring_force, inc.spring);
                if (d.spring_first[inc.spring] == i)
                    total += f;
                else
                    total -= f;
            }
            for (std::int64_t e = anchor_offsets_[p]; e < anchor_offsets_[p + 1]; ++e) {
                const std::int64_t a = anchor_index_[static_cast<std::size_t>(e)];
                total += d.anchor_stiffness[a] * (row(anchors, a) - x) - d.anchor_damping[a] * v;
            }
            for (std::int64_t e = muscle_offsets_[p]; e < muscle_offsets_[p + 1]; ++e) {
                const std::int64_t m = muscle_of_entry_[static_cast<std::size_t>(e)];
                const double magnitude = controls.contractions[m] * d.muscle_max_force[m] *
                                         weight_of_entry_[static_cast<std::size_t>(e)];
                if (magnitude == 0.0) continue;
                Vec3 toward = row(attachments, m) - x;
                if (d.muscle_kind[m] == kSphincterMuscle) {
                    // Toward the epicentre within the ellipse's plane.
                    const Vec3 a = d.muscle_axes.row(m).segment<3>(0).transpose();
                    const Vec3 b = d.muscle_axes.row(m).segment<3>(3).transpose();
                    toward = a.dot(toward) * a + b.dot(toward) * b;
                }
                // Within kMuscleCore of the attachment (or the sphincter's axis) the pull
                // fades linearly to zero: tissue is not pulled past a muscle's origin, and
                // a direction that flips there would make the particle chatter about it.
                const double length = toward.norm();
                if (length > 0.0) total += magnitude / std::max(length, kMuscleCore) * toward;
            }
            const std::int64_t foot = state.foot[i];
            if (foot >= 0 && skull.vertices.rows() > 0 && d.contact_stiffness[i] > 0.0) {
                const SkullContact contact = locate(x, foot, skull);
                if (contact.height < d.contact_margin[i])
                    total += (d.contact_stiffness[i] * (d.contact_margin[i] - contact.height) -
                              d.contact_damping[i] * v.dot(contact.normal)) *
                             contact.normal;
            }
            out.row(i) = total.transpose();
        }
    });
}

Points SkinSystem::forces(const SkinState& state, const SkinControls& controls) const {
    const JawMotion jaw(data_.jaw_pivot, data_.jaw_axis, controls.jaw_angle);
    const Points anchors = bone_points(data_.anchor_target, data_.anchor_bone, jaw);
    const Points attachments = muscle_points(jaw);
    const SkullGeometry skull = skull_at(controls);
    Points out;
    accumulate_forces(state, controls, anchors, attachments, skull, out);
    return out;
}

double SkinSystem::potential_energy(const PointsRef& positions,
                                    const SkinControls& controls) const {
    const SkinSystemData& d = data_;
    const JawMotion jaw(d.jaw_pivot, d.jaw_axis, controls.jaw_angle);
    double energy = 0.0;
    for (Eigen::Index s = 0; s < d.spring_first.size(); ++s) {
        const double length =
            (row(positions, d.spring_second[s]) - row(positions, d.spring_first[s])).norm();
        energy += biphasic_energy(length - d.spring_rest[s], d.spring_rest[s],
                                  d.spring_stiffness[s], d.spring_stiffness_high[s],
                                  d.spring_knee[s]);
    }
    for (Eigen::Index a = 0; a < d.anchor_particle.size(); ++a) {
        const Vec3 target = jaw.apply(row(d.anchor_target, a), d.anchor_bone[a]);
        energy += 0.5 * d.anchor_stiffness[a] *
                  (row(positions, d.anchor_particle[a]) - target).squaredNorm();
    }
    for (Eigen::Index q = 0; q < d.prism_particles.rows(); ++q) {
        const double change = prism_volume(d, positions, q).volume - d.prism_rest_volume[q];
        energy += 0.5 * d.prism_stiffness[q] * change * change;
    }
    return energy;
}

double SkinSystem::kinetic_energy(const PointsRef& velocities) const {
    double energy = 0.0;
    for (Eigen::Index i = 0; i < data_.masses.size(); ++i)
        energy += 0.5 * data_.masses[i] * velocities.row(i).squaredNorm();
    return energy;
}

SkullGeometry SkinSystem::skull_at(const SkinControls& controls) const {
    const SkinSystemData& d = data_;
    const JawMotion jaw(d.jaw_pivot, d.jaw_axis, controls.jaw_angle);
    SkullGeometry skull;
    skull.vertices = bone_points(d.skull_vertices, d.skull_bone, jaw);
    skull.normals.resize(d.skull_normals.rows(), 3);
    for (Eigen::Index v = 0; v < skull.normals.rows(); ++v) {
        const Vec3 rest = d.skull_normals.row(v).transpose();
        skull.normals.row(v) =
            (d.skull_bone[v] == kMandible ? Vec3(jaw.rotation * rest) : rest).transpose();
    }
    skull.face_normals.resize(d.skull_faces.rows(), 3);
    for (Eigen::Index f = 0; f < d.skull_faces.rows(); ++f) {
        const Vec3 a = row(skull.vertices, d.skull_faces(f, 0));
        const Vec3 normal = (row(skull.vertices, d.skull_faces(f, 1)) - a)
                                .cross(row(skull.vertices, d.skull_faces(f, 2)) - a);
        const double length = normal.norm();
        skull.face_normals.row(f) = (length > 0.0 ? Vec3(normal / length) : Vec3::Zero()).transpose();
    }
    return skull;
}

VectorX SkinSystem::skull_heights(const PointsRef& positions, const Eigen::Ref<const IndexVector>& foot,
                                  const SkinControls& controls) const {
    VectorX heights = VectorX::Zero(positions.rows());
    if (data_.skull_vertices.rows() == 0) return heights;
    const SkullGeometry skull = skull_at(controls);
    parallel_for(static_cast<std::size_t>(positions.rows()), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t i = begin; i < end; ++i) {
            const auto k = static_cast<Eigen::Index>(i);
            if (foot[k] >= 0) heights[k] = locate(positions.row(k).transpose(), foot[k], skull).height;
        }
    });
    return heights;
}

void SkinSystem::project_contacts(SkinState& state, const SkinControls& controls) const {
    const SkinSystemData& d = data_;
    if (d.skull_vertices.rows() == 0) return;
    const SkullGeometry skull = skull_at(controls);
    const std::int64_t n = particles();
    parallel_for(static_cast<std::size_t>(n), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            std::int64_t foot = state.foot[static_cast<Eigen::Index>(p)];
            if (foot < 0) continue;
            const Vec3 x = row(state.positions, static_cast<std::int64_t>(p));
            // Walk downhill over the skull's vertices to the nearest one: tissue slides
            // a few millimetres per step at most, so this takes a step or two. The walk
            // stays on the particle's own bone: where the open jaw pulls the skull
            // apart, a particle hopping between the two parts would meet surfaces that
            // disagree and chatter between them.
            const std::int64_t bone = d.skull_bone[foot];
            double best = (row(skull.vertices, foot) - x).squaredNorm();
            for (int walk = 0; walk < 64; ++walk) {
                std::int64_t next = foot;
                for (std::int64_t e = d.skull_indptr[foot]; e < d.skull_indptr[foot + 1]; ++e) {
                    const std::int64_t v = d.skull_neighbours[e];
                    if (d.skull_bone[v] != bone) continue;
                    const double dist = (row(skull.vertices, v) - x).squaredNorm();
                    if (dist < best) {
                        best = dist;
                        next = v;
                    }
                }
                if (next == foot) break;
                foot = next;
            }
            state.foot[static_cast<Eigen::Index>(p)] = foot;
            const SkullContact contact = locate(x, foot, skull);
            if (contact.height >= 0.0) continue;
            state.positions.row(static_cast<Eigen::Index>(p)) = contact.point.transpose();
            const Vec3 v = row(state.velocities, static_cast<std::int64_t>(p));
            const double inward = v.dot(contact.normal);
            if (inward < 0.0)
                state.velocities.row(static_cast<Eigen::Index>(p)) =
                    (v - inward * contact.normal).transpose();
        }
    });
}

Points SkinSystem::free_forces(const SkinState& state, const SkinControls& controls) const {
    const SkinSystemData& d = data_;
    Points force = forces(state, controls);
    if (d.skull_vertices.rows() == 0) return force;
    const SkullGeometry skull = skull_at(controls);
    // A particle counts as lying on the skull within a hair of its surface (the
    // projection puts it exactly there, up to rounding).
    const double touching = 1e-9;
    for (Eigen::Index i = 0; i < force.rows(); ++i) {
        const std::int64_t foot = state.foot[i];
        if (foot < 0) continue;
        const SkullContact contact = locate(row(state.positions, i), foot, skull);
        if (contact.height > touching) continue;
        const double inward = force.row(i).dot(contact.normal.transpose());
        if (inward < 0.0) force.row(i) -= inward * contact.normal.transpose();
    }
    return force;
}

void SkinSystem::step_symplectic(SkinState& state, const SkinControls& controls,
                                 double dt) const {
    const Points force = forces(state, controls);
    const std::int64_t n = particles();
    parallel_for(static_cast<std::size_t>(n), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            const Eigen::Index i = static_cast<Eigen::Index>(p);
            state.velocities.row(i) += (dt / data_.masses[i]) * force.row(i);
            state.positions.row(i) += dt * state.velocities.row(i);
        }
    });
    project_contacts(state, controls);
}

void SkinSystem::assemble(const SkinState& state, const SkinControls& controls, double dt,
                          std::vector<double>& values, Points& kv) const {
    // The matrix M + dt D + dt^2 K, block column by block column: a particle owns its
    // three columns, so the fill runs in parallel without conflicts. The geometric part
    // of a spring's stiffness, (F / l)(I - d d^T), is kept only in tension, so the
    // matrix stays positive definite; the contact penalty counts where a particle is in
    // the contact zone. Muscles stay explicit (their directions turn slowly).
    const SkinSystemData& d = data_;
    const std::int64_t n = particles();
    const double h = dt, h2 = dt * dt;
    kv.resize(n, 3);
    const SkullGeometry skull = skull_at(controls);
    // Each prism's volume gradient g (6 x 3) and g . v: its stiffness is k g g^T.
    const std::int64_t prisms = static_cast<std::int64_t>(d.prism_particles.rows());
    Points gradient(6 * prisms, 3);
    VectorX rate(prisms);
    parallel_for(static_cast<std::size_t>(prisms), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t q = begin; q < end; ++q) {
            const std::int64_t k = static_cast<std::int64_t>(q);
            gradient.middleRows<6>(6 * k) = prism_volume(d, state.positions, k).gradient;
            double dv = 0.0;
            for (int c = 0; c < 6; ++c)
                dv += gradient.row(6 * k + c).dot(state.velocities.row(d.prism_particles(k, c)));
            rate[k] = dv;
        }
    });
    parallel_for(static_cast<std::size_t>(n), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            const std::int64_t j = static_cast<std::int64_t>(p);
            const Vec3 x = row(state.positions, j);
            const Vec3 v = row(state.velocities, j);
            Mat3 diagonal = d.masses[j] * (1.0 + h * d.drag) * Mat3::Identity();
            Vec3 stiffness_times_v = Vec3::Zero();
            for (std::int64_t e = spring_offsets_[p]; e < spring_offsets_[p + 1]; ++e) {
                const Incidence& inc = spring_incidence_[static_cast<std::size_t>(e)];
                const SpringState s = evaluate_spring(d, inc.spring, x, row(state.positions, inc.other));
                const Mat3 along = s.direction * s.direction.transpose();
                Mat3 stiffness = s.slope * along;
                if (s.force > 0.0 && s.length > 0.0)
                    stiffness += (s.force / s.length) * (Mat3::Identity() - along);
                stiffness_times_v += stiffness * (v - row(state.velocities, inc.other));
                const Mat3 block = h * d.spring_damping[inc.spring] * along + h2 * stiffness;
                diagonal += block;
                if (inc.other > j) {
                    const std::int64_t slot = spring_block_[inc.spring];
                    for (int c = 0; c < 3; ++c) {
                        const std::int64_t at = pattern_indptr_[3 * j + c] + (3 - c) + 3 * slot;
                        for (int r = 0; r < 3; ++r) values[at + r] -= block(r, c);
                    }
                }
            }
            for (std::int64_t e = prism_offsets_[p]; e < prism_offsets_[p + 1]; ++e) {
                const std::int64_t entry = prism_corner_[static_cast<std::size_t>(e)];
                const std::int64_t q = entry / 6;
                const int c = static_cast<int>(entry % 6);
                const double k = d.prism_stiffness[q];
                const Vec3 own = row(gradient, entry);
                stiffness_times_v += k * rate[q] * own;
                diagonal += h2 * k * own * own.transpose();
                for (int r = 0; r < 6; ++r) {
                    const std::int64_t slot = prism_block_[static_cast<std::size_t>(36 * q + 6 * c + r)];
                    if (slot < 0) continue;
                    const Mat3 block = h2 * k * row(gradient, 6 * q + r) * own.transpose();
                    for (int cc = 0; cc < 3; ++cc) {
                        const std::int64_t at = pattern_indptr_[3 * j + cc] + (3 - cc) + 3 * slot;
                        for (int rr = 0; rr < 3; ++rr) values[at + rr] += block(rr, cc);
                    }
                }
            }
            for (std::int64_t e = anchor_offsets_[p]; e < anchor_offsets_[p + 1]; ++e) {
                const std::int64_t a = anchor_index_[static_cast<std::size_t>(e)];
                diagonal += (h * d.anchor_damping[a] + h2 * d.anchor_stiffness[a]) * Mat3::Identity();
                stiffness_times_v += d.anchor_stiffness[a] * v;
            }
            const std::int64_t foot = state.foot[j];
            if (foot >= 0 && d.contact_stiffness[j] > 0.0 && d.skull_vertices.rows() > 0) {
                const SkullContact contact = locate(x, foot, skull);
                if (contact.height < d.contact_margin[j]) {
                    const Mat3 along = contact.normal * contact.normal.transpose();
                    diagonal += (h * d.contact_damping[j] + h2 * d.contact_stiffness[j]) * along;
                    stiffness_times_v += d.contact_stiffness[j] * along * v;
                }
            }
            kv.row(j) = stiffness_times_v.transpose();
            for (int c = 0; c < 3; ++c) {
                const std::int64_t at = pattern_indptr_[3 * j + c];
                for (int r = c; r < 3; ++r) values[at + (r - c)] = diagonal(r, c);
            }
        }
    });
}

void SkinSystem::step_implicit(SkinState& state, const SkinControls& controls, double dt) {
    // (M + dt D + dt^2 K) dv = dt (f + dt (df/dx) v) = dt (f - dt K v)
    const std::int64_t n = particles();
    const Points force = forces(state, controls);
    if (!factor_)
        factor_ = std::make_unique<PatternCholesky>(3 * n, pattern_indptr_.data(), pattern_indices_.data(), nullptr);
    std::vector<double> values(pattern_indices_.size(), 0.0);
    Points kv;
    assemble(state, controls, dt, values, kv);
    factor_->factorize(values.data(), kPivotTolerance);
    Eigen::VectorXd rhs(3 * n);
    for (std::int64_t j = 0; j < n; ++j)
        rhs.segment<3>(3 * j) = dt * (force.row(j) - dt * kv.row(j)).transpose();
    const Eigen::MatrixXd dv = factor_->solve(rhs);
    parallel_for(static_cast<std::size_t>(n), kMinChunk, [&](std::size_t begin, std::size_t end) {
        for (std::size_t p = begin; p < end; ++p) {
            const Eigen::Index i = static_cast<Eigen::Index>(p);
            state.velocities.row(i) += dv.block<3, 1>(3 * i, 0).transpose();
            state.positions.row(i) += dt * state.velocities.row(i);
        }
    });
    project_contacts(state, controls);
}

void SkinSystem::step(SkinState& state, const SkinControls& controls, double dt,
                      SkinIntegrator integrator) {
    if (integrator == SkinIntegrator::symplectic)
        step_symplectic(state, controls, dt);
    else
        step_implicit(state, controls, dt);
}

SkinRunReport SkinSystem::run(SkinState& state, const SkinControls& target,
                              const SkinRunSettings& settings) {
    const std::int64_t n = particles();
    const double dt = settings.dt;
    SkinRunReport report;
    const Points rest = state.positions;
    auto record = [&](double time) {
        if (settings.record_count <= 0) return;
        report.frame_times.push_back(time);
        for (std::int64_t i = 0; i < settings.record_count; ++i)
            for (int c = 0; c < 3; ++c) report.frames.push_back(state.positions(i, c));
    };
    auto controls_at = [&](double time) {
        const double s = settings.ramp_time > 0.0 ? smoothstep(time / settings.ramp_time) : 1.0;
        SkinControls c;
        c.contractions = s * target.contractions;
        c.jaw_angle = s * target.jaw_angle;
        return c;
    };
    if (settings.record_every > 0) record(0.0);
    std::int64_t calm = 0;
    std::int64_t last_recorded = 0;
    for (std::int64_t k = 0; k < settings.max_steps; ++k) {
        const double start = k * dt;
        // The rest test looks at the state before the step, under the full controls.
        if (start >= settings.ramp_time && k % std::max<std::int64_t>(settings.check_every, 1) == 0) {
            const Points force = free_forces(state, target);
            double speed = 0.0, residual = 0.0;
            for (std::int64_t i = 0; i < n; ++i) {
                speed = std::max(speed, state.velocities.row(i).norm());
                residual = std::max(residual, force.row(i).norm() / data_.rest_stiffness[i]);
            }
            report.max_speed = speed;
            report.max_residual = residual;
            const bool calm_now =
                speed < settings.velocity_tolerance && residual < settings.force_tolerance;
            calm = calm_now ? calm + 1 : 0;
            if (calm >= settings.patience) {
                report.settled = true;
                break;
            }
        }
        // Controls at the end of the step: the implicit step is evaluated there, and
        // the semi-implicit one reaches the target one step sooner; both reach it.
        step(state, controls_at(start + dt), dt, settings.integrator);
        report.steps = k + 1;
        report.time = (k + 1) * dt;
        bool finite = true;
        double far = 0.0;
        for (std::int64_t i = 0; i < n; ++i) {
            finite = finite && state.positions.row(i).allFinite() && state.velocities.row(i).allFinite();
            far = std::max(far, (state.positions.row(i) - rest.row(i)).norm());
        }
        if (!finite || far > settings.divergence_distance) {
            report.diverged = true;
            break;
        }
        if (settings.record_every > 0 && report.steps % settings.record_every == 0) {
            record(report.time);
            last_recorded = report.steps;
        }
    }
    if (settings.record_every > 0 && last_recorded != report.steps && !report.diverged)
        record(report.time);
    return report;
}

}  // namespace tpscore
